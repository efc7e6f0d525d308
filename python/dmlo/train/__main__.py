"""``python -m dmlo.train`` (e.g. under ``torchrun --nproc_per_node N``): the same options as ``dmlo train``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from typing import Any

from dmlo.cli import UserError
from dmlo.commands.train import add_arguments, run


def main(argv: list[str] | None = None, options: Mapping[str, Any] | None = None) -> int:
    """`dmlo train` with `argv`; `options`: `TrainConfig` fields the command line does not take."""
    parser = argparse.ArgumentParser(prog="python -m dmlo.train", description=__doc__)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args, options)
    except UserError as err:
        print(f"dmlo.train: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
