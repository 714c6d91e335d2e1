"""A caching C compiler front end for CasADi's JIT (``NMPCConfig(jit=True)``).

CasADi's shell compiler calls ``<compiler> <flags> -c <source> -o <object>`` for every JIT build.
The generated source of the NMPC's NLP is the same in every process with the same settings, so
this front end keys the object file on a hash of the compiler, the flags and the source, and
copies it from the cache instead of compiling again (~30-80 s saved per process here).

Cache: ``$UAVTRACK_JIT_CACHE`` or ``~/.cache/uavtrack/casadi-jit``. Compiler: ``$CC``, else gcc or
cc on the PATH. ``$UAVTRACK_JIT=0`` turns off the default compile (`NMPCConfig.jit` None).
Run as ``python jit_cache.py <compiler args>`` (the path goes into CasADi's ``jit_options``).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def cache_dir() -> Path:
    """Where compiled objects are kept."""
    env = os.environ.get("UAVTRACK_JIT_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "uavtrack" / "casadi-jit"


def compiler() -> str | None:
    """The C compiler JIT builds use: ``$CC``, else gcc or cc on the PATH; None if none."""
    if os.environ.get("CC"):
        return os.environ["CC"]
    return next((c for c in ("gcc", "cc") if shutil.which(c)), None)


def auto_enabled() -> bool:
    """Whether `NMPCConfig.jit` None compiles: a compiler exists and ``$UAVTRACK_JIT`` is not 0."""
    return os.environ.get("UAVTRACK_JIT", "1") != "0" and compiler() is not None


def _source_and_output(args: list[str]) -> tuple[str | None, str | None]:
    src = next((a for a in args if a.endswith(".c")), None)
    out = args[args.index("-o") + 1] if "-o" in args[:-1] else None
    return src, out


def main(args: list[str]) -> int:
    """Compile (or fetch from the cache) one object file; returns the compiler's exit code."""
    cc = compiler() or "gcc"
    src, out = _source_and_output(args)
    if src is None or out is None or "-c" not in args:  # not a plain compile: pass through
        return subprocess.call([cc, *args])
    digest = hashlib.sha256()
    digest.update(" ".join([cc, *(a for a in args if a not in (src, out))]).encode())
    digest.update(Path(src).read_bytes())
    cached = cache_dir() / f"{digest.hexdigest()}.o"
    if cached.is_file():
        shutil.copyfile(cached, out)
        return 0
    print(
        f"uavtrack: compiling the NMPC's {Path(src).stem!r} functions with {cc} for these "
        f"settings (once; 20-80 s; kept in {cache_dir()}; UAVTRACK_JIT=0 skips it)",
        file=sys.stderr,
        flush=True,
    )
    code = subprocess.call([cc, *args])
    if code == 0:
        cached.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=cached.parent, suffix=".tmp")
        os.close(fd)
        shutil.copyfile(out, tmp)
        os.replace(tmp, cached)  # atomic: parallel builds never see a partial object
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
