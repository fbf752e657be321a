"""Entry point of ``gf-cli``. Each command lives in its own module with ``register(sub)``."""

from __future__ import annotations

import argparse
import sys

from gf_core.errors import GFError

from . import (cmd_addon, cmd_bench, cmd_demo, cmd_edit, cmd_evaluate, cmd_export, cmd_inspect, cmd_predict,
               cmd_reconstruct, cmd_render_dataset, cmd_simulate)

COMMANDS = [cmd_demo, cmd_simulate, cmd_render_dataset, cmd_reconstruct, cmd_evaluate, cmd_predict, cmd_edit,
            cmd_export, cmd_inspect, cmd_bench, cmd_addon]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="gf-cli",
        description="GaussFluids: reconstruct Lagrangian fluid particles from multiview videos "
                    "with differentiable Gaussian splatting.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for mod in COMMANDS:
        mod.register(sub)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except GFError as e:
        print(f"gf-cli {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gf-cli {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
