"""Runnable training: shared-parameter PPO with SB3 (``python -m train.ppo``), shielded or not."""
