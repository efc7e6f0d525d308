"""The installed package: version, command line, and the type stubs against the compiled module."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import dmlo
import dmlo_rs
from support import REPO

STUBTEST_ALLOWLIST = Path(__file__).with_name("stubtest_allowlist.txt")


def test_versions_agree() -> None:
    assert dmlo_rs.__version__ == dmlo.__version__


def test_command_line_reports_version() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "dmlo", "--version"], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == f"dmlo {dmlo.__version__}"


def test_stubs_match_the_extension_module() -> None:
    # stubtest imports the real module and checks every name, signature and class in the .pyi files.
    out = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "dmlo_rs._dmlo_rs", "--allowlist", str(STUBTEST_ALLOWLIST)],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr


def test_package_reexports_the_whole_extension() -> None:
    from dmlo_rs import _dmlo_rs

    assert dmlo_rs.__all__ == _dmlo_rs.__all__
    assert all(getattr(dmlo_rs, name) is getattr(_dmlo_rs, name) for name in dmlo_rs.__all__)


def test_the_python_package_type_checks() -> None:
    # The typed API is part of the product: mypy must accept the whole package as written.
    package = Path(dmlo.__file__).parent
    out = subprocess.run(
        [sys.executable, "-m", "mypy", str(package), "--ignore-missing-imports", "--no-error-summary"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_benchmark_scripts_type_check() -> None:
    # They left the wheel for the checkout's benchmarks/ folder, and with it the package's check above.
    scripts = REPO / "benchmarks"
    out = subprocess.run(
        [sys.executable, "-m", "mypy", str(scripts), "--ignore-missing-imports", "--no-error-summary"],
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr


def test_every_command_has_help_with_examples() -> None:
    from dmlo.cli import _COMMANDS

    for command in _COMMANDS:
        out = subprocess.run(
            [sys.executable, "-m", "dmlo", command, "--help"], capture_output=True, text=True, check=True
        )
        assert "\nexamples:\n  " in out.stdout, command
        # A default is shown only when it says something, and once.
        text = " ".join(out.stdout.split())
        assert "(default: None)" not in text and "(default: [])" not in text, command
        assert ") (default:" not in text, command
