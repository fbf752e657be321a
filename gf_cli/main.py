"""Entry point of ``gf-cli``. Each command lives in its own module with ``register(sub)``."""

from __future__ import annotations

import argparse
import os
import sys

# The simulation commands run the native SPH engine, whose OpenMP threads meet at a barrier many
# times per step. Spinning there (libgomp's default) makes a run several times slower as soon as
# anything else uses the cores; sleeping costs a little on an idle machine (BENCHMARKS.md, "Native
# SPH engine", busy machine). OpenMP reads this when it loads, with torch, so it is set here,
# before any import of torch, for these commands only; a setting of the user's own wins.
SIM_COMMANDS = ("simulate", "predict", "edit")
if len(sys.argv) > 1 and sys.argv[1] in SIM_COMMANDS and not {"OMP_WAIT_POLICY", "GOMP_SPINCOUNT"} & set(os.environ):
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

from gf_core.errors import GFError  # noqa: E402

from . import (cmd_addon, cmd_batch, cmd_bench, cmd_demo, cmd_edit, cmd_evaluate, cmd_export, cmd_inspect,  # noqa: E402
               cmd_predict, cmd_reconstruct, cmd_render_dataset, cmd_simulate)

COMMANDS = [cmd_demo, cmd_simulate, cmd_render_dataset, cmd_reconstruct, cmd_evaluate, cmd_predict, cmd_edit,
            cmd_export, cmd_inspect, cmd_bench, cmd_batch, cmd_addon]


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


cmd_demo.dispatch = main

if __name__ == "__main__":
    sys.exit(main())
