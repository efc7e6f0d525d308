"""Whether this processor runs the compiled extension, asked before it is imported.

On x86-64 the extension is built for x86-64-v3 without FMA (AVX2 and its companions; `.cargo/config.toml`):
Intel's processors since Haswell and AMD's since Excavator have them, not every Pentium, Celeron or Atom. On
one without them, importing it would kill the interpreter with SIGILL, an illegal instruction, and no message.
So where `/proc/cpuinfo` lacks a v3 feature the extension is first imported in a child process: if the child
dies of SIGILL, the import here raises an `ImportError` that names what is missing and how to build for this
processor; otherwise (a build for the baseline, made with `RUSTFLAGS`) the import goes on.
"""

from __future__ import annotations

import os
import platform
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

# The flags `/proc/cpuinfo` shows for the features x86-64-v3 adds to the baseline (v2's included; FMA, which
# the build leaves out, excepted), by the name people know them by.
X86_64_V3_FLAGS = {
    "cx16": "CMPXCHG16B",
    "lahf_lm": "LAHF/SAHF",
    "popcnt": "POPCNT",
    "pni": "SSE3",
    "ssse3": "SSSE3",
    "sse4_1": "SSE4.1",
    "sse4_2": "SSE4.2",
    "avx": "AVX",
    "avx2": "AVX2",
    "bmi1": "BMI1",
    "bmi2": "BMI2",
    "f16c": "F16C",
    "abm": "LZCNT",
    "movbe": "MOVBE",
    "xsave": "XSAVE",
}

# Set in the child that tries the import, so that its own `import dmlo_rs` does not ask again.
TRIAL_VARIABLE = "DMLO_RS_INSTRUCTION_SET_TRIAL"

REBUILD = (
    "build dmlo_rs for this processor instead: RUSTFLAGS='-C target-cpu=native -C target-feature=-fma' "
    "maturin develop --release "
    "(or the same variable before `pip install`)"
)


def missing_features(cpuinfo: str) -> list[str]:
    """The x86-64-v3 features the first processor of a `/proc/cpuinfo` text lacks (none: an empty list)."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            flags = set(value.split())
            return [name for flag, name in X86_64_V3_FLAGS.items() if flag not in flags]
    return []


def extension_imports() -> int:
    """The exit status of a child process that imports the extension (negative: the signal that killed it)."""
    # The child searches where this interpreter does, which may be more than its environment says.
    env = {**os.environ, TRIAL_VARIABLE: "1", "PYTHONPATH": os.pathsep.join(path for path in sys.path if path)}
    return subprocess.run([sys.executable, "-c", "import dmlo_rs._dmlo_rs"], env=env, check=False).returncode


def check_instruction_set(
    cpuinfo: Path = Path("/proc/cpuinfo"),
    machine: str | None = None,
    trial: Callable[[], int] = extension_imports,
) -> None:
    """Raises `ImportError` where the extension would die of an illegal instruction on this processor."""
    if os.environ.get(TRIAL_VARIABLE):
        return
    if (machine or platform.machine()).lower() not in ("x86_64", "amd64") or not cpuinfo.is_file():
        return
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:  # unreadable here (a sandbox): nothing to judge by, as on a system without the file
        return
    missing = missing_features(text)
    if not missing:
        return
    status = trial()
    if status == -signal.SIGILL:
        raise ImportError(
            f"dmlo_rs was built for x86-64-v3 and this processor lacks {', '.join(missing)}: importing it dies of "
            f"an illegal instruction; {REBUILD}"
        )
