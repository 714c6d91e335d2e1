"""Markdown pages for docs/results/ from run directories (metrics.json beside config.json).

    python -m baselines.report                          # docs/results/NAME/ -> docs/results/NAME.md
    python -m baselines.report --results runs/mine      # any directory of run directories

Every sub-directory NAME of the results directory that holds a ``metrics.json`` (one episode's
dict from ``python -m baselines.evaluate``, or a list of them from ``--all`` or
``baselines.compare``) becomes ``NAME.md``: a title, one line of settings, the table (Table VI's
form from `baselines.evaluate.table`, or `baselines.compare.comparison_table` for policy
comparisons), a few counted facts and a stamp with the run's command and commit, read from
``NAME/config.json`` (or the ``"config"`` key of metrics.json; "unknown" without either). Then
``README.md`` indexes every page of the directory, generated or written by hand.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
from pathlib import Path

from .evaluate import table
from .paper_results import TABLE_VI

INDEX = "README.md"
STAGES = ("ukf", "nmpc", "qp", "policy", "env")


def run_dirs(results: Path) -> list[Path]:
    """The sub-directories of ``results`` that hold a metrics.json, sorted by name."""
    if not results.is_dir():
        raise FileNotFoundError(
            f"results directory {results} does not exist (expected DIR/NAME/metrics.json)"
        )
    return sorted(d for d in results.iterdir() if (d / "metrics.json").is_file())


def load_runs(run_dir: Path) -> list[dict]:
    """The episodes of ``run_dir/metrics.json`` as a list (one dict or a list of dicts)."""
    data = json.loads((run_dir / "metrics.json").read_text())
    runs = data if isinstance(data, list) else [data]
    if not runs or not all(isinstance(m, dict) and "uavs" in m for m in runs):
        raise ValueError(f"{run_dir / 'metrics.json'}: expected episode dicts with a 'uavs' key")
    return runs


def load_config(run_dir: Path, runs: list[dict]) -> dict:
    """``run_dir/config.json``, else the ``"config"`` of the first episode, else {}."""
    path = run_dir / "config.json"
    if path.is_file():
        return json.loads(path.read_text())
    config = runs[0].get("config")
    return config if isinstance(config, dict) else {}


def is_comparison(runs: list[dict], config: dict) -> bool:
    """True for ``baselines.compare`` / ``train.*`` episodes: a table per policy and world."""
    command = command_text(config)
    if "baselines.evaluate" in command:
        return False
    return all("violation_steps" in m for m in runs)


def is_paper(runs: list[dict]) -> bool:
    """True when every episode is a row of the paper's Table VI (its RMS errors can be shown)."""
    return all((m.get("scenario"), m.get("init")) in TABLE_VI for m in runs)


def command_text(config: dict) -> str:
    """The run's command as one shell line ("unknown" when not recorded)."""
    command = config.get("command")
    if not command:
        return "unknown"
    return shlex.join(map(str, command)) if isinstance(command, list) else str(command)


def settings_line(runs: list[dict], config: dict) -> str:
    """One line: worlds, episode length, dynamics, seeds, preset."""
    worlds = []
    for m in runs:
        name = "random" if m.get("scenario") == "random" else f"{m.get('scenario')}{m.get('init')}"
        if name not in worlds:
            worlds.append(name)
    seeds = sorted({m["seed"] for m in runs if "seed" in m})
    durations = sorted({round(m["duration_s"], 2) for m in runs if "duration_s" in m})
    dynamics = sorted({str(m["dynamics"]) for m in runs if "dynamics" in m})
    env = config.get("env") if isinstance(config.get("env"), dict) else {}
    if not dynamics and isinstance(env.get("dynamics"), dict):
        dynamics = [str(env["dynamics"].get("model"))]
    parts = [f"Worlds: {', '.join(worlds)}"]
    if durations:
        parts.append(f"episodes of {'/'.join(f'{d:g}' for d in durations)} s")
    if dynamics:
        parts.append(f"dynamics {'/'.join(dynamics)}")
    if seeds:
        parts.append("seed " + (f"{seeds[0]}" if len(seeds) == 1 else f"{seeds[0]}-{seeds[-1]}"))
    parts.append(f"preset `{config.get('preset', 'unknown')}`")
    return "; ".join(parts) + "."


def facts(runs: list[dict], paper: bool) -> list[str]:
    """Counted facts below the table: safety flags, the paper's RMS, median stage times."""
    rows = [(m, i, r) for m in runs for i, r in enumerate(m["uavs"].values())]
    safe = sum(r["collision_ok"] and r["connectivity_ok"] and r["occlusion_ok"] for _, _, r in rows)
    lines = [f"UAV rows with Occlusion, Connectivity and Collision all Y: {safe} of {len(rows)}."]
    if paper:
        ref = [TABLE_VI[(m["scenario"], m["init"])][i] for m, i, _ in rows]
        below_u = sum(r["rms_u_px"] < p[0] for (_, _, r), p in zip(rows, ref, strict=True))
        below_v = sum(r["rms_v_px"] < p[1] for (_, _, r), p in zip(rows, ref, strict=True))
        lines.append(
            f"Below the paper's RMS error: U in {below_u} of {len(rows)} rows, "
            f"V in {below_v} of {len(rows)}."
        )
    spans = []
    for stage in STAGES:
        values = [
            float(m["timing_ms"][stage])
            for m in runs
            if isinstance(m.get("timing_ms", {}).get(stage), (int, float))
            and math.isfinite(m["timing_ms"][stage])
        ]
        if values:
            lo, hi = min(values), max(values)
            spans.append(f"{stage} {lo:.2f}" + (f"-{hi:.2f}" if hi > lo else ""))
    if spans:
        lines.append(f"Median time per UAV-step (ms, range over episodes): {', '.join(spans)}.")
    return lines


def render(run_dir: Path) -> str:
    """The markdown page of one run directory."""
    runs = load_runs(run_dir)
    config = load_config(run_dir, runs)
    if is_comparison(runs, config):
        from .compare import comparison_table

        body, notes = comparison_table(runs), []
    else:
        paper = is_paper(runs)
        body, notes = table(runs, paper=paper), facts(runs, paper)
    stamp = (
        f"Generated by `python -m baselines.report` from `{run_dir.name}/metrics.json`. "
        f"Run: `{command_text(config)}`; commit `{config.get('commit') or 'unknown'}`."
    )
    parts = [f"# {run_dir.name}", settings_line(runs, config), body]
    if notes:
        parts.append("\n".join(f"- {n}" for n in notes))
    parts.append(stamp)
    return "\n\n".join(parts) + "\n"


def title_of(page: Path) -> str:
    """The first markdown heading of ``page`` (its file name without one)."""
    for line in page.read_text().splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    return page.stem


def index(results: Path, generated: list[str]) -> str:
    """README.md of the results directory: one row per page."""
    lines = [
        "# Results",
        "",
        "Each page named after a run directory `NAME/` (its `metrics.json` and `config.json`) is",
        "generated by `python -m baselines.report`; rerun it after adding or replacing a run.",
        "The other pages are written by hand. Table VI per preset P (`tuned`, `paper-planner`,",
        "`paper`): `python -m baselines.evaluate --all --no-figures --preset P --out",
        "docs/results/table6-P`, then `python -m baselines.report` writes `table6-P.md`.",
        "",
        "| page | title | source |",
        "|---|---|---|",
    ]
    for page in sorted(results.glob("*.md")):
        if page.name == INDEX:
            continue
        source = f"`{page.stem}/metrics.json`" if page.stem in generated else "by hand"
        lines.append(f"| [{page.name}]({page.name}) | {title_of(page)} | {source} |")
    return "\n".join(lines) + "\n"


def generate(results: Path) -> list[Path]:
    """Write NAME.md for every run directory and the index; returns the pages written."""
    written = []
    dirs = run_dirs(results)
    for run_dir in dirs:
        page = results / f"{run_dir.name}.md"
        page.write_text(render(run_dir))
        written.append(page)
    (results / INDEX).write_text(index(results, [d.name for d in dirs]))
    return [*written, results / INDEX]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    ap = argparse.ArgumentParser(prog="python -m baselines.report", description=__doc__)
    ap.add_argument(
        "--results",
        type=Path,
        default=Path("docs/results"),
        help="directory of run directories NAME/metrics.json (default: docs/results)",
    )
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> list[Path]:
    """Generate the pages; a missing directory or a malformed metrics.json exits with a message."""
    args = parse_args(argv)
    try:
        written = generate(args.results)
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"baselines.report: {err}") from err
    for page in written:
        print(f"wrote {page}")
    return written


if __name__ == "__main__":
    main()
