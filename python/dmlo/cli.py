"""The ``dmlo`` command: one subcommand per job, each registered from its own module."""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from collections.abc import Callable, Sequence

import dmlo


class DefaultsAndExamplesFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows each option's default and keeps the examples in the epilog as written."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        # "(default: None)" says nothing, and a help text that names its default already says it better.
        text = action.help or ""
        if action.default in (None, False, []) or "default" in text:
            return action.help
        return super()._get_help_string(action)


class UserError(Exception):
    """A mistake in what the user asked for: printed as one line, no traceback."""


def _integer_at_least(least: int, meaning: str) -> Callable[[str], int]:
    """An argparse ``type`` for integers ``>= least``: argparse reports a refusal naming the flag."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"must be {meaning} (>= {least}), got {value}")
        return value

    parse.__name__ = f"integer >= {least}"  # how argparse names the type in its own messages
    return parse


# The optional packages a command may need and the extra of pyproject.toml that installs each
# (tests/cli/test_dependencies.py holds this table to pyproject.toml).
EXTRA_OF_PACKAGE = {
    "torch": "train",
    "onnx": "train",
    "onnxscript": "train",
    "scipy": "train",
    "matplotlib": "plot",
    "lzf": "io",
    "pyarrow": "argoverse2",
    "kiss_icp": "bench",
    "small_gicp": "bench",
    "open3d": "bench",
}


def missing_extra_message(err: ModuleNotFoundError) -> str | None:
    """For an optional package that is not installed, what to install; None for any other module."""
    package = (err.name or "").split(".")[0]
    extra = EXTRA_OF_PACKAGE.get(package)
    return None if extra is None else f"{package} is not installed: pip install 'dmlo[{extra}]'"


positive_int = _integer_at_least(1, "a positive integer")
non_negative_int = _integer_at_least(0, "a non-negative integer")


# One module per subcommand under `dmlo.commands`, each with `register(subparsers)` that adds its parser
# and sets `run`. Command modules import heavy libraries (torch, onnxruntime) inside `run` only, so
# `dmlo --help` stays fast and the odometry never imports torch.
_COMMANDS: list[str] = ["demo", "run", "register", "bench", "simulate", "eval", "train", "export"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dmlo",
        description="DMLO: Deep Matching LiDAR Odometry.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"dmlo {dmlo.__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        module = importlib.import_module(f"dmlo.commands.{name}")
        module.register(subparsers)
    return parser


def _one_line_warning(command: str) -> Callable[..., None]:
    """Warnings meant for the user read as one line, like the errors (not as a source location), and
    on a line of their own above a progress bar."""

    def show(message: Warning | str, *_args: object, **_kwargs: object) -> None:
        from tqdm import tqdm

        tqdm.write(f"dmlo {command}: warning: {message}", file=sys.stderr)

    return show


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "run"):
        parser.print_help()
        return 0
    warnings.showwarning = _one_line_warning(args.command)
    try:
        return int(args.run(args) or 0)
    except UserError as err:
        print(f"dmlo {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dmlo {args.command}: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as err:  # an optional extra the command needs: say which, in one line
        message = missing_extra_message(err)
        if message is None:
            raise
        print(f"dmlo {args.command}: error: {message}", file=sys.stderr)
        return 1
    except OSError as err:  # a full disk, a file in the way, no permission: what and where, in one line
        from dmlo.outputs import describe_os_error

        where = f"{err.filename}: " if getattr(err, "filename", None) else ""
        print(f"dmlo {args.command}: error: {where}{describe_os_error(err)}", file=sys.stderr)
        return 1
