"""``gf-cli edit RUN --at T (--remove-fraction F | --remove-box ... | --add-box ... | --translate ...)``:
edit the reconstructed particles, then continue them with a simulator (paper Sec. 4.3.5, Fig. 10)."""

from __future__ import annotations

from .cmd_predict import add_continuation_options, load_state, simulate_state


def register(sub):
    p = sub.add_parser("edit", help="edit the reconstructed fluid (remove, add, move particles) and simulate on",
                       description="Edit the reconstructed particles at time T, then simulate them on as gf-cli "
                                   "predict does. Edits apply in this order: removals (fraction, box, sphere), "
                                   "translation, addition. Added particles fill the box on a lattice at the "
                                   "particles' spacing and take the appearance of their nearest particle.")
    add_continuation_options(p)
    p.add_argument("--remove-fraction", type=float, default=None, metavar="F",
                   help="remove a random fraction F of the particles (Fig. 10: 0.5)")
    p.add_argument("--remove-box", type=float, nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="remove the particles inside this box (metres)")
    p.add_argument("--remove-sphere", type=float, nargs=4, default=None, metavar=("CX", "CY", "CZ", "R"),
                   help="remove the particles inside this sphere (metres)")
    p.add_argument("--translate", type=float, nargs=3, default=None, metavar=("DX", "DY", "DZ"),
                   help="move every particle by this offset (metres)")
    p.add_argument("--add-box", type=float, nargs=6, default=None, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                   help="add fluid filling this box (metres)")
    p.add_argument("--add-velocity", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("VX", "VY", "VZ"),
                   help="initial velocity of the added fluid, m/s (default 0 0 0)")
    p.add_argument("--seed", type=int, default=0, help="random seed of --remove-fraction (default 0)")
    p.set_defaults(func=run)


def _box(vals, flag):
    import numpy as np

    from gf_core.errors import InputError

    lo, hi = np.asarray(vals[:3], float), np.asarray(vals[3:], float)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
        raise InputError(flag, f"needs X0 Y0 Z0 X1 Y1 Z1 with X1 > X0, Y1 > Y0, Z1 > Z0; got {list(vals)}")
    return lo, hi


def run(args) -> int:
    import math

    from gf_core.downstream import edit as E
    from gf_core.downstream import predict as P
    from gf_core.errors import InputError

    if all(v is None for v in (args.remove_fraction, args.remove_box, args.remove_sphere, args.translate,
                               args.add_box)):
        raise InputError("edit", "no edit given: use --remove-fraction, --remove-box, --remove-sphere, --translate "
                                 "or --add-box (gf-cli predict continues without editing)")
    from gf_core.limits import check_seed

    check_seed("--seed", args.seed)
    if args.remove_fraction is not None and not 0 <= args.remove_fraction < 1:
        raise InputError("--remove-fraction", f"must be in [0, 1), got {args.remove_fraction}")
    boxes = {f: _box(v, f) for f, v in (("--remove-box", args.remove_box), ("--add-box", args.add_box)) if v}
    if args.remove_sphere and not (args.remove_sphere[3] > 0 and all(map(math.isfinite, args.remove_sphere))):
        raise InputError("--remove-sphere", f"needs CX CY CZ R with R > 0, got {args.remove_sphere}")
    for flag, v in (("--translate", args.translate), ("--add-velocity", args.add_velocity)):
        if v is not None and not all(map(math.isfinite, v)):
            raise InputError(flag, f"must be 3 finite numbers, got {list(v)}")
    recon, _, s, fps = load_state(args)
    s = P.keep_rest_state(s, args.solver)  # the particles keep their mass whatever is removed or added
    if args.remove_fraction is not None:
        s = E.remove_fraction(s, args.remove_fraction, seed=args.seed)
    if "--remove-box" in boxes:
        s = E.remove_box(s, *boxes["--remove-box"])
    if args.remove_sphere:
        s = E.remove_sphere(s, args.remove_sphere[:3], args.remove_sphere[3])
    if args.translate:
        s = E.translate(s, args.translate)
    if "--add-box" in boxes:
        s = E.add_box(s, *boxes["--add-box"], P.rest_state(s, args.solver)[0], velocity=args.add_velocity)
    for e in s.edits:
        print("edit:", ", ".join(f"{k} {v}" for k, v in e.items()))
    return simulate_state(args, recon, s, fps, "edit")
