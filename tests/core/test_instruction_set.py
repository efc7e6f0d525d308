"""The check before the extension is imported: a processor without x86-64-v3's features gets an `ImportError`
that names them, not an interpreter killed by an illegal instruction; one with them is never slowed down."""

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from dmlo_rs._instruction_set import X86_64_V3_FLAGS, check_instruction_set, extension_imports, missing_features

ALL_FLAGS = " ".join(["fpu", "sse", "sse2", *X86_64_V3_FLAGS])


def cpuinfo(tmp_path: Path, flags: str) -> Path:
    path = tmp_path / "cpuinfo"
    path.write_text(f"processor\t: 0\nmodel name\t: a processor\nflags\t\t: {flags}\n\nprocessor\t: 1\nflags\t\t: {flags}\n")
    return path


def never(name: str):  # type: ignore[no-untyped-def]
    def trial() -> int:
        raise AssertionError(f"{name}: the extension was tried in a child although no feature is missing")

    return trial


def test_missing_features_are_named_as_people_know_them() -> None:
    assert missing_features(f"flags\t: {ALL_FLAGS}\n") == []
    without = ALL_FLAGS.replace(" avx2", "").replace(" abm", "")
    assert missing_features(f"flags\t: {without}\n") == ["AVX2", "LZCNT"]
    assert missing_features("processor\t: 0\n") == [], "no flags line (another kernel's format): nothing to judge"


def test_a_processor_with_every_feature_imports_without_a_trial(tmp_path: Path) -> None:
    check_instruction_set(cpuinfo(tmp_path, ALL_FLAGS), machine="x86_64", trial=never("v3"))


def test_other_machines_are_not_judged_by_x86_flags(tmp_path: Path) -> None:
    check_instruction_set(cpuinfo(tmp_path, "fp asimd"), machine="aarch64", trial=never("aarch64"))
    check_instruction_set(tmp_path / "absent", machine="x86_64", trial=never("no cpuinfo"))


def test_an_unreadable_cpuinfo_is_not_judged(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = cpuinfo(tmp_path, "fpu sse sse2")

    def refused(self: Path, *args: object, **kwargs: object) -> str:
        raise PermissionError(f"{self}: permission denied")

    monkeypatch.setattr(Path, "read_text", refused)
    check_instruction_set(path, machine="x86_64", trial=never("unreadable cpuinfo"))


def test_a_build_that_dies_of_an_illegal_instruction_is_refused_by_name(tmp_path: Path) -> None:
    old = cpuinfo(tmp_path, ALL_FLAGS.replace(" avx2", "").replace(" movbe", ""))
    with pytest.raises(ImportError, match=r"lacks AVX2, MOVBE.*target-cpu=native"):
        check_instruction_set(old, machine="x86_64", trial=lambda: -signal.SIGILL)


def test_a_build_for_the_baseline_imports_on_an_old_processor(tmp_path: Path) -> None:
    old = cpuinfo(tmp_path, ALL_FLAGS.replace(" avx2", ""))
    check_instruction_set(old, machine="x86_64", trial=lambda: 0)
    # Another failure in the child is left to the import itself, which raises it with its own message.
    check_instruction_set(old, machine="x86_64", trial=lambda: 1)


def test_the_trial_imports_the_extension_in_a_child_that_does_not_check_again() -> None:
    assert extension_imports() == 0


def test_an_interpreter_that_dies_of_an_illegal_instruction_reports_the_signal() -> None:
    """What `extension_imports` relies on: a child killed by SIGILL has the negated signal as its status."""
    code = "import os, signal; os.kill(os.getpid(), signal.SIGILL)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == -signal.SIGILL
