"""``gf-cli evaluate RUN``: image metrics per split/view/frame, density spread, particle error."""

from __future__ import annotations

from pathlib import Path


def register(sub):
    p = sub.add_parser("evaluate", help="judge a reconstruction: PSNR/SSIM, density spread, particle error",
                       description="Render the reconstruction into every image of the dataset (training views and "
                                   "held-out views = novel-view synthesis) and report PSNR and SSIM per split, view "
                                   "and frame; the per-frame standard deviation of the SPH density D_i (paper "
                                   "Fig. 4); with ground-truth particles, the mean distance from each true particle "
                                   "to the nearest reconstructed one and back, in true particle spacings. Writes "
                                   "RUN/eval.json and PNG plots (including PSNR against wall-clock seconds from "
                                   "metrics.jsonl).")
    p.add_argument("run", type=Path, help="run folder (holding recon.h5), a recon.h5 file, or a sim.h5 from "
                                          "gf-cli predict/edit (rendered with the learned appearance)")
    p.add_argument("--dataset", type=Path, default=None,
                   help="dataset folder (default: the one recorded in recon.h5, if it still exists)")
    p.add_argument("--gt", type=Path, default=None,
                   help="ground-truth sim.h5 (default: the dataset's gt_sim.h5, if any)")
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default: the run folder)")
    p.add_argument("--fps", type=float, default=None, help="frame rate for normalised-time datasets (default: the dataset's)")
    p.add_argument("--duration", type=float, default=None, help="clip length in seconds for normalised time (default: the dataset's)")
    p.add_argument("--rest-density", type=float, default=None,
                   help="kg/m^3 for particle masses in the energies (default: the ground truth's, else 1000)")
    p.add_argument("--upsample", type=int, default=None, metavar="K",
                   help="temporal resampling (paper Table 7): render the training views at K x the training frame "
                        "rate from the decoder (PNGs in OUT/upsample_xK/), score the frames held out in time "
                        "(reconstruct --frames ::2) against frame repetition and linear blending, and measure "
                        "jitter (default: off)")
    p.set_defaults(func=run)


def run(args) -> int:
    from gf_core.data import has_split, load_dataset
    from gf_core.errors import InputError
    from gf_core.eval.evaluate import evaluate, evaluate_continuation
    from gf_core.formats.hdf5 import SIM_FORMAT, file_format, read_recon, read_sim

    from .options import check_device

    device = check_device(args.device)
    if args.upsample is not None and args.upsample < 1:
        raise InputError("--upsample", f"must be an integer >= 1, got {args.upsample}")
    if args.rest_density is not None and not args.rest_density > 0:
        raise InputError("--rest-density", f"must be > 0 kg/m^3, got {args.rest_density}")
    if args.out is not None:
        from .options import check_out_dir

        check_out_dir(args.out)
    recon = args.run / "recon.h5" if args.run.is_dir() else args.run
    if not recon.exists():
        raise InputError(recon, "no reconstruction here (run gf-cli reconstruct first)")
    continuation = file_format(recon) == SIM_FORMAT
    if continuation:
        sim = read_sim(recon)
        if not sim.config.get("recon"):
            raise InputError(recon, "is a simulation, not a continuation of a reconstruction (gf-cli predict/edit)")
        recon = Path(sim.config["recon"])
    r = read_recon(recon)
    ds_path = args.dataset
    if ds_path is None:
        rec = r.config.get("dataset")
        if rec and Path(rec).exists():
            ds_path = Path(rec)
    train = test = None
    if ds_path is not None:
        # the images as the reconstruction read them (channels, background removal, size)
        kw = dict(r.config.get("dataset_options") or {}, grayscale=r.channels == 1, fps=args.fps,
                  duration=args.duration)
        train = load_dataset(ds_path, **kw)
        if has_split(ds_path, "test"):
            test = load_dataset(ds_path, split="test", **kw)
    if continuation:
        evaluate_continuation(args.run, dataset=train, test_dataset=test, gt_path=args.gt, device=device, out=args.out)
    else:
        if args.upsample and train is None:
            raise InputError("--upsample", "needs the dataset: give --dataset")
        evaluate(args.run, dataset=train, test_dataset=test, gt_path=args.gt, device=device, out=args.out,
                 rest_density=args.rest_density, upsample=args.upsample)
    return 0
