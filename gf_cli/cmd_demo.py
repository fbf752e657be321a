"""``gf-cli demo``: the whole toolkit on the built-in scene, one stage after another, each through
the same ``gf-cli`` command a user would type, and an HTML report of everything.

  1 simulate     water_sphere with DFSPH                              -> OUT/sim.h5
  2 render       5 training + 1 held-out view with Blender (Cycles)   -> OUT/dataset/
  3 reconstruct  the first frames of the clip (the rest is for 5)     -> OUT/run/recon.h5
  4 evaluate     held-out views, density, energy, particle error      -> OUT/run/eval.json + plots
  5 predict      continue the last reconstructed frame with PBF,
                 judged against the frames the reconstruction never saw -> OUT/predict/predict.h5
  6 edit         remove half the fluid, simulate on                   -> OUT/predict/edit.h5
  7 export       3DGS PLY and USD points                              -> OUT/export/
  8 blender      the reconstruction in Blender through the extension,
                 two looks                                            -> OUT/blender/look_*.png
  9 report       one self-contained page                              -> OUT/report.html

A stage whose outputs exist and which finished with the same settings is skipped on a re-run
(``OUT/demo_state.json``); when one is redone, every later stage is redone too. ``--force``
redoes them all. ``--quick`` runs every stage at tiny sizes (the test suite runs it).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path


@dataclass(frozen=True)
class Sizes:
    particles: int
    seconds: float
    fps: float
    resolution: int
    samples: int
    train_frames: int       # reconstructed: the first train_frames frames; the rest are predicted
    time_budget: float      # reconstruct --time-budget (s); 0: iterations only
    iterations: int
    init_particles: int
    max_particles: int
    predict_frames: int
    look_resolution: int
    look_samples: int


FULL = Sizes(particles=2000, seconds=1.0, fps=30.0, resolution=128, samples=16, train_frames=20, time_budget=480.0,
             iterations=100000, init_particles=2000, max_particles=4000, predict_frames=10, look_resolution=320,
             look_samples=32)
QUICK = Sizes(particles=300, seconds=0.3, fps=20.0, resolution=48, samples=4, train_frames=5, time_budget=0.0,
              iterations=150, init_particles=250, max_particles=400, predict_frames=2, look_resolution=64,
              look_samples=4)

STAGES = ("simulate", "render", "reconstruct", "evaluate", "predict", "edit", "export", "blender", "report")


def register(sub):
    p = sub.add_parser("demo", help="the whole toolkit on the built-in scene, with an HTML report",
                       description="Simulate the built-in water_sphere scene, render it with Blender (5 training "
                                   "views + 1 held out), reconstruct it, evaluate it, predict and edit a "
                                   "continuation, export PLY/USD, render the reconstruction in Blender through the "
                                   "extension in two looks, and write OUT/report.html. Finished stages are skipped "
                                   "on a re-run.")
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    p.add_argument("--quick", action="store_true", help="tiny sizes, every stage, a few minutes (default: off)")
    p.add_argument("--force", action="store_true", help="redo every stage (default: skip finished ones)")
    p.add_argument("--device", default="cpu", help="cpu or cuda for reconstruction and evaluation (default cpu)")
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help=f"reconstruction wall-clock budget (default {FULL.time_budget:g}; --quick: "
                        f"{QUICK.iterations} iterations)")
    p.set_defaults(func=run)


class Demo:
    def __init__(self, out: Path, sizes: Sizes, device: str, force: bool):
        self.out, self.z, self.device, self.force = out, sizes, device, force
        self.state_file = out / "demo_state.json"
        self.sim, self.dataset = out / "sim.h5", out / "dataset"
        self.run_dir, self.pred_dir = out / "run", out / "predict"
        self.settings = {"sizes": asdict(sizes), "device": device}
        st = {}
        if self.state_file.exists():
            try:
                st = json.loads(self.state_file.read_text())
            except json.JSONDecodeError:
                st = {}
        self.done = st.get("done", {}) if st.get("settings") == self.settings and not force else {}
        self.redo_rest = False
        self.summary: dict = {}

    def outputs(self, stage: str) -> list[Path]:
        return {"simulate": [self.sim], "render": [self.dataset / "transforms_train.json",
                                                   self.dataset / "transforms_test.json"],
                "reconstruct": [self.run_dir / "recon.h5"], "evaluate": [self.run_dir / "eval.json"],
                "predict": [self.pred_dir / "predict.h5", self.pred_dir / "predict_eval.json"],
                "edit": [self.pred_dir / "edit.h5"],
                "export": [self.out / "export" / "gaussians.ply", self.out / "export" / "particles.usdc"],
                "blender": [self.out / "blender" / "look_water.png", self.out / "blender" / "look_pink.png"],
                "report": [self.out / "report.html"]}[stage]

    def save(self):
        from gf_core.formats.hdf5 import atomic_write_text

        atomic_write_text(self.state_file, json.dumps({"settings": self.settings, "done": self.done}, indent=1))

    def stage(self, k: int, name: str, fn) -> None:
        head = f"[{k}/{len(STAGES)}] {name}"
        if not self.redo_rest and name in self.done and all(p.exists() for p in self.outputs(name)):
            self.summary[name] = self.done[name]
            print(f"{head}: done before ({self.done[name].get('seconds', 0):.0f} s), skipped", flush=True)
            return
        self.redo_rest = True  # what follows depends on this stage's outputs
        self.done.pop(name, None)
        print(f"{head} ...", flush=True)
        t0 = time.perf_counter()
        info = fn() or {}
        info["seconds"] = round(time.perf_counter() - t0, 1)
        missing = [str(p) for p in self.outputs(name) if not p.exists()]
        if missing:
            from gf_core.errors import GFError

            raise GFError(f"demo stage {name} finished without writing {', '.join(missing)}")
        self.done[name] = self.summary[name] = info
        self.save()
        print(f"{head}: {info['seconds']:.1f} s", flush=True)


# gf-cli's own entry point, set by ``main.py`` (which registers this command): the demo runs the
# other commands as a user would, in this process
dispatch = None


def gf(*argv) -> None:
    """Run one gf-cli command as a user would; a failure stops the demo with its message."""
    from gf_core.errors import GFError

    argv = [str(a) for a in argv]
    print("  $ gf-cli " + " ".join(argv), flush=True)
    rc = dispatch(argv)
    if rc != 0:
        raise GFError(f"demo: `gf-cli {' '.join(argv)}` failed (exit {rc}); see the message above")


def run(args) -> int:
    import importlib.util
    import shutil

    from gf_core.errors import GFError, InputError

    from .options import check_device

    if importlib.util.find_spec("bpy") is None and shutil.which("blender") is None:
        raise GFError(f"the demo renders with Blender: install the bpy module (pip install 'bpy==5.0.1', which needs "
                      f"Python 3.11; this is Python {sys.version.split()[0]}) or put `blender` on PATH")
    check_device(args.device)
    z = QUICK if args.quick else FULL
    if args.time_budget is not None:
        if not args.time_budget > 0:
            raise InputError("--time-budget", f"must be a positive number of seconds, got {args.time_budget}")
        from dataclasses import replace

        z = replace(z, time_budget=float(args.time_budget), iterations=max(z.iterations, 100000))
    out = args.out
    if out.exists() and not out.is_dir():
        raise InputError(out, "--out must be a folder, and this is a file")
    out.mkdir(parents=True, exist_ok=True)
    d = Demo(out, z, args.device, args.force)
    t_all = time.perf_counter()
    n_frames = int(round(z.seconds * z.fps)) + 1
    t_last = (z.train_frames - 1) / z.fps  # the last reconstructed frame: where prediction starts

    def simulate():
        gf("simulate", "water_sphere", "--out", d.sim, "--particles", z.particles, "--fps", z.fps,
           "--seconds", z.seconds)
        from gf_core.formats.hdf5 import read_sim

        s = read_sim(d.sim)
        return {"particles": s.num_particles, "frames": s.num_frames,
                "density_error_final": float(s.stats["density_err_mean"][-1])}

    def render():
        gf("render-dataset", d.sim, "--out", d.dataset, "--views", 5, "--test-views", 1, "--resolution",
           z.resolution, "--samples", z.samples, "--force")
        return {"images": len(list(d.dataset.rglob("*.png"))), "resolution": z.resolution}

    def reconstruct():
        cfg = out / "demo_config.toml"
        cfg.write_text("# written by gf-cli demo: phases end at their share of the time budget (or iteration count)\n"
                       "[phases]\nplateau_window = 100000\n[train]\neval_every = 250\n")
        extra = ["--time-budget", z.time_budget] if z.time_budget else []
        gf("reconstruct", d.dataset, "--out", d.run_dir, "--frames", f"0:{z.train_frames}", "--config", cfg,
           "--iterations", z.iterations, "--init-particles", z.init_particles, "--max-particles", z.max_particles,
           "--device", args.device, "--force", *extra)
        from gf_core.formats.hdf5 import read_recon

        m = read_recon(d.run_dir / "recon.h5").metrics
        return {"particles": m["particles"], "iterations": m["iterations"], "wall_s": round(m["wall_s"], 1)}

    def evaluate():
        gf("evaluate", d.run_dir, "--dataset", d.dataset, "--device", args.device)
        ev = json.loads((d.run_dir / "eval.json").read_text())
        pv = ev.get("particles_vs_gt", {})
        en = ev["energy"]["per_frame"]
        return {"test_psnr": ev["test"]["psnr_mean"], "test_ssim": ev["test"]["ssim_mean"],
                "train_psnr": ev["train"]["psnr_mean"], "density_std": ev["density"]["std_mean"],
                "gt_to_recon": pv.get("gt_to_recon_mean"), "recon_to_gt": pv.get("recon_to_gt_mean"),
                "energy_start_J": en[0]["total"], "energy_end_J": en[-1]["total"]}

    def predict():
        gf("predict", d.run_dir, "--at", t_last, "--frames", z.predict_frames, "--fps", z.fps,
           "--out", d.pred_dir / "predict.h5", "--quiet")
        gf("evaluate", d.pred_dir / "predict.h5", "--dataset", d.dataset, "--device", args.device)
        ev = json.loads((d.pred_dir / "predict_eval.json").read_text())
        return {"frames": z.predict_frames, "test_psnr": ev.get("test", {}).get("psnr_mean"),
                "train_psnr": ev.get("train", {}).get("psnr_mean"),
                "chamfer_last": ev.get("particles_vs_gt", {}).get("chamfer_last")}

    def edit():
        gf("edit", d.run_dir, "--at", t_last, "--remove-fraction", 0.5, "--frames", z.predict_frames, "--fps", z.fps,
           "--out", d.pred_dir / "edit.h5", "--quiet")
        from gf_core.formats.hdf5 import read_sim

        e = read_sim(d.pred_dir / "edit.h5")
        return {"particles": e.num_particles, "frames": e.num_frames - 1}

    def export():
        gf("export", d.run_dir, "--format", "ply", "--time", t_last / 2, "--out", out / "export" / "gaussians.ply")
        gf("export", d.run_dir, "--format", "usd", "--out", out / "export" / "particles.usdc")
        return {"ply_bytes": (out / "export" / "gaussians.ply").stat().st_size,
                "usd_bytes": (out / "export" / "particles.usdc").stat().st_size}

    def blender():
        return render_looks(d, t_last / 2, z)

    def report():
        from . import demo_report

        demo_report.write(d, t_last)
        return {"bytes": (out / "report.html").stat().st_size}

    for k, (name, fn) in enumerate(zip(STAGES, (simulate, render, reconstruct, evaluate, predict, edit, export,
                                                 blender, report)), 1):
        d.stage(k, name, fn)
    print_summary(d, time.perf_counter() - t_all)
    return 0


def render_looks(d: Demo, t: float, z: Sizes) -> dict:
    """The extension as a user installs it (zip with the h5py wheel for this machine), in a Blender
    whose user folders live in OUT/blender/home, rendering the reconstruction at ``t`` in two looks."""
    import os
    import platform
    import subprocess

    from gf_core.errors import GFError

    from .cmd_addon import PLATFORMS, build

    plat = {("linux", "x86_64"): "linux-x64", ("darwin", "arm64"): "macos-arm64", ("darwin", "x86_64"): "macos-x64",
            ("win32", "AMD64"): "windows-x64"}.get((sys.platform, platform.machine()))
    if plat not in PLATFORMS:
        raise GFError(f"the extension has no build for {sys.platform} {platform.machine()}")
    bdir = d.out / "blender"
    cache = Path(os.environ.get("GF_WHEEL_CACHE", Path.home() / ".cache" / "gaussfluids" / "wheels"))
    zip_path = build(bdir, [plat], cache)
    import render_data

    script = Path(render_data.__file__).with_name("showcase.py")
    env = dict(os.environ, HOME=str((bdir / "home").resolve()))
    cmd = [sys.executable, str(script), str(zip_path), str(d.run_dir / "recon.h5"), str(d.dataset), str(bdir),
           "--time", f"{t:.6f}", "--res", str(z.look_resolution), "--samples", str(z.look_samples),
           "--fps", f"{z.fps:g}", "--looks", "water,pink"]
    print("  $ " + " ".join(cmd[1:3]) + " ...", flush=True)
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise GFError(f"rendering with the Blender extension failed (exit {r.returncode}):\n{r.stderr[-3000:]}")
    return {"zip": zip_path.name, "looks": ["water", "pink"], "resolution": z.look_resolution}


def print_summary(d: Demo, wall: float) -> None:
    s = d.summary

    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    ev, pr = s.get("evaluate", {}), s.get("predict", {})
    rows = [
        ("simulate", f"{s['simulate']['particles']} particles, {s['simulate']['frames']} frames"),
        ("render", f"{s['render']['images']} images at {s['render']['resolution']} px"),
        ("reconstruct", f"{s['reconstruct']['particles']} particles, {s['reconstruct']['iterations']} iterations, "
                        f"{s['reconstruct']['wall_s']} s"),
        ("evaluate", f"held-out PSNR {f(ev.get('test_psnr'), '.2f')} dB, SSIM {f(ev.get('test_ssim'), '.3f')}; "
                     f"true->recon {f(ev.get('gt_to_recon'), '.2f')}, recon->true {f(ev.get('recon_to_gt'), '.2f')} "
                     f"spacings; density std {f(ev.get('density_std'), '.3f')}"),
        ("predict", f"{pr.get('frames')} frames: held-out-view PSNR {f(pr.get('test_psnr'), '.2f')} dB, Chamfer at "
                    f"the last frame {f(pr.get('chamfer_last'), '.2f')} spacings"),
        ("edit", f"{s['edit']['particles']} particles after removing half"),
        ("export", f"PLY {s['export']['ply_bytes'] // 1024} kB, USD {s['export']['usd_bytes'] // 1024} kB"),
        ("blender", f"looks {', '.join(s['blender']['looks'])} at {s['blender']['resolution']} px"),
        ("report", str(d.out / "report.html")),
    ]
    width = max(len(r[0]) for r in rows)
    print("\nstage" + " " * (width - 3) + "seconds  result")
    for name, text in rows:
        print(f"{name:<{width}}  {s[name]['seconds']:7.1f}  {text}")
    print(f"\ndemo finished in {wall:.0f} s (stages skipped as done count their earlier time above); "
          f"open {d.out / 'report.html'}")
