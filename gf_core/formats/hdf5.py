"""File formats: ``sim.h5`` (simulated particles) and ``recon.h5`` (a reconstruction).

Both are HDF5, self-describing (root attributes ``format`` and ``version``), validated on read
(format, version, required fields, shapes, finite values) and written atomically: the data go to
a temporary file beside the target, which is renamed over it only when complete, so a killed run
never leaves a half-written file that looks complete. Nothing is ever loaded with pickle.
The schemas are documented in ``docs/formats.md``.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError, short_repr

SIM_FORMAT, SIM_VERSION = "gaussfluids.sim", 1
# version 2 adds the optional decoder residuals, version 3 the optional colour and opacity residuals, version 4
# residuals of the canonical frame's own (decoder encoding "canonical_residual"); a file is
# written with the lowest version that holds what it has (without residuals: 1), so older readers
# still read what they can render correctly
RECON_FORMAT, RECON_VERSION = "gaussfluids.recon", 4
RECON_VERSIONS_READ = (1, 2, 3, 4)
GRID_FORMAT, GRID_VERSION = "gaussfluids.grid", 1


# ---- helpers -------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(path: "str | os.PathLike[str]"):
    """Yield a temporary path next to ``path``; rename it onto ``path`` if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        # mkstemp makes the file 0600; a result gets the mode any new file gets (0644 under umask 022)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@contextlib.contextmanager
def output_lock(target, what: str):
    """Hold ``.NAME.lock`` beside the output ``target`` (a file or a folder) for the block, so
    that a second process writing the same output is refused at once with one line instead of
    mixing its frames or images in. The lock file sits outside the output (a ``--force`` that
    clears the output keeps it) and is removed on release; the lock goes with the process, so a
    killed run leaves nothing that blocks a resume."""
    import fcntl

    target = Path(target).resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    lock = target.parent / f".{target.name}.lock"
    while True:
        f = open(lock, "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            f.close()
            raise InputError(target, f"another process ({holder}) is writing this {what}; wait for it to "
                                     "finish or choose another --out") from None
        try:  # the holder before us may have removed the file between our open and our lock
            same = os.fstat(f.fileno()).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        f.close()
    try:
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()}")
        f.flush()
        yield
    finally:
        try:
            os.unlink(lock)
        except FileNotFoundError:
            pass
        f.close()


def atomic_write_text(path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def _h5():
    import h5py

    return h5py


def file_format(path) -> str | None:
    """The ``format`` attribute of an HDF5 file (``gaussfluids.sim`` / ``gaussfluids.recon``), or
    None for a file that is not one of ours."""
    h5py = _h5()
    try:
        with h5py.File(Path(path), "r") as f:
            v = f.attrs.get("format")
    except OSError:
        return None
    v = v.decode(errors="replace") if isinstance(v, bytes) else v
    return v if isinstance(v, str) else None


def _open_checked(path, fmt: str, version: int):
    """Open an HDF5 file for reading and check its format/version attributes."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file does not exist")
    h5py = _h5()
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise FormatError(path, f"not a readable HDF5 file ({e})") from None
    got_fmt = f.attrs.get("format")
    got_fmt = got_fmt.decode() if isinstance(got_fmt, bytes) else got_fmt
    if not isinstance(got_fmt, str) or got_fmt != fmt:
        f.close()
        raise FormatError(path, f"expected format {fmt!r}, found {short_repr(got_fmt)}")
    raw_ver = f.attrs.get("version", -1)
    versions = version if isinstance(version, tuple) else (version,)
    try:
        got_ver = int(raw_ver) if np.ndim(raw_ver) == 0 and float(raw_ver) == int(raw_ver) else None
    except (TypeError, ValueError, OverflowError):
        got_ver = None
    if got_ver not in versions:
        f.close()
        raise FormatError(path, f"{fmt} version {short_repr(raw_ver)} is not supported (this toolkit reads "
                                f"version {' and '.join(map(str, versions))})")
    return f



def _read(f, name: str, path, *, ndim: int | None = None, shape_tail: tuple | None = None,
          dtype=np.float32, finite: bool = True) -> np.ndarray:
    if name not in f:
        raise FormatError(path, f"missing dataset {name!r}")
    a = np.asarray(f[name][()])
    if a.dtype.kind not in "biuf":
        raise FormatError(path, f"dataset {name!r} must hold numbers, holds {a.dtype} ({short_repr(a)})")
    if ndim is not None and a.ndim != ndim:
        raise FormatError(path, f"dataset {name!r} must have {ndim} dimensions, has shape {a.shape}")
    if shape_tail is not None and tuple(a.shape[-len(shape_tail):]) != tuple(shape_tail):
        raise FormatError(path, f"dataset {name!r} must have shape (..., "
                                f"{', '.join(map(str, shape_tail))}), has {a.shape}")
    a = a.astype(dtype, copy=False)
    if finite and not np.all(np.isfinite(a)):
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        raise FormatError(path, f"dataset {name!r} contains {bad} NaN or infinite values")
    return a


def _attr(f, name: str, path, cast=float):
    if name not in f.attrs:
        raise FormatError(path, f"missing attribute {name!r}")
    v = f.attrs[name]
    if isinstance(v, bytes):
        v = v.decode()
    if cast is str and not isinstance(v, str):
        raise FormatError(path, f"attribute {name!r} must be a string, got {short_repr(v)}")
    try:
        if np.ndim(v) != 0:
            raise TypeError
        v = cast(v)
    except (TypeError, ValueError, OverflowError):
        raise FormatError(path, f"attribute {name!r} has an invalid value {short_repr(v)}") from None
    if cast is float and not np.isfinite(v):
        raise FormatError(path, f"attribute {name!r} is not finite ({v})")
    return v


def _json_attr(f, name: str, path) -> dict:
    raw = f.attrs.get(name, "{}")
    raw = raw.decode(errors="replace") if isinstance(raw, bytes) else raw
    if not isinstance(raw, str):
        raise FormatError(path, f"attribute {name!r} must be a JSON string, got {short_repr(raw)}")
    try:
        d = json.loads(raw)
    except json.JSONDecodeError as e:
        raise FormatError(path, f"attribute {name!r} is not valid JSON ({e})") from None
    except RecursionError:
        raise FormatError(path, f"attribute {name!r} is JSON nested too deeply") from None
    if not isinstance(d, dict):
        raise FormatError(path, f"attribute {name!r} must be a JSON object, got {short_repr(d)}")
    return d


def _check_finite(name: str, a: np.ndarray, where: str) -> None:
    if not np.all(np.isfinite(a)):
        raise InputError(where, f"{name} contains NaN or infinite values; refusing to write")


# ---- sim.h5 --------------------------------------------------------------------------------------
@dataclass
class SimData:
    """Particles per frame from a simulator (or a reconstruction's continuation).

    positions, velocities: (F, N, 3) float32, metres and m/s; times: (F,) seconds.
    """

    positions: np.ndarray
    velocities: np.ndarray
    fps: float
    particle_radius: float
    rest_density: float = 1000.0
    viscosity: float = 0.0
    gravity: tuple = (0.0, 0.0, -9.81)
    solver: str = ""
    domain_min: tuple = (0.0, 0.0, 0.0)
    domain_max: tuple = (1.0, 1.0, 1.0)
    scene: str = ""
    times: np.ndarray | None = None
    config: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)  # per-frame arrays, e.g. density_error_mean (F,)
    complete: bool = True      # False: a run stopped early; the frames written so far
    # a continuation of a reconstruction (gf-cli predict/edit): for each particle, the index of the
    # reconstructed particle whose appearance (Gaussian scale, rotation, opacity, colour) it keeps
    source_index: np.ndarray | None = None

    def __post_init__(self):
        self.positions = np.asarray(self.positions, np.float32)
        self.velocities = np.asarray(self.velocities, np.float32)
        if self.positions.ndim != 3 or self.positions.shape[-1] != 3:
            raise InputError("sim data", f"positions must be (frames, particles, 3), got {self.positions.shape}")
        if self.velocities.shape != self.positions.shape:
            raise InputError("sim data", f"velocities {self.velocities.shape} must match positions {self.positions.shape}")
        if self.times is None:
            self.times = np.arange(self.positions.shape[0], dtype=np.float64) / float(self.fps)
        self.times = np.asarray(self.times, np.float64)
        if self.times.shape != (self.positions.shape[0],):
            raise InputError("sim data", f"times must be ({self.positions.shape[0]},), got {self.times.shape}")
        if self.source_index is not None:
            self.source_index = np.asarray(self.source_index, np.int64)
            if self.source_index.shape != (self.positions.shape[1],):
                raise InputError("sim data", f"source_index must be ({self.positions.shape[1]},), "
                                             f"got {self.source_index.shape}")

    @property
    def num_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def num_particles(self) -> int:
        return self.positions.shape[1]


def check_sim(sim: SimData, where: str) -> None:
    """What ``read_sim`` would refuse, refused before writing."""
    _check_finite("positions", sim.positions, where)
    _check_finite("velocities", sim.velocities, where)
    for name in ("fps", "particle_radius", "rest_density"):
        v = float(getattr(sim, name))
        if not (np.isfinite(v) and v > 0):
            raise InputError(where, f"{name} must be a positive number, got {v}; refusing to write")
    if not np.isfinite(float(sim.viscosity)) or sim.viscosity < 0:
        raise InputError(where, f"viscosity must be >= 0, got {sim.viscosity}; refusing to write")
    dmin, dmax = np.asarray(sim.domain_min, float), np.asarray(sim.domain_max, float)
    if dmin.shape != (3,) or dmax.shape != (3,) or not (np.all(np.isfinite(dmin)) and np.all(np.isfinite(dmax))) \
            or np.any(dmax <= dmin):
        raise InputError(where, f"domain_max {dmax.tolist()} must exceed domain_min {dmin.tolist()}; refusing to write")
    g = np.asarray(sim.gravity, float)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise InputError(where, f"gravity must be 3 finite numbers, got {sim.gravity}; refusing to write")
    if not np.all(np.isfinite(sim.times)):
        raise InputError(where, "times contain NaN or infinite values; refusing to write")


def write_sim(path, sim: SimData) -> Path:
    """Write ``sim`` to ``path`` atomically. Refuses what ``read_sim`` would refuse."""
    path = Path(path)
    check_sim(sim, str(path))
    h5py = _h5()
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = SIM_FORMAT
            f.attrs["version"] = SIM_VERSION
            f.attrs["fps"] = float(sim.fps)
            f.attrs["particle_radius"] = float(sim.particle_radius)
            f.attrs["rest_density"] = float(sim.rest_density)
            f.attrs["viscosity"] = float(sim.viscosity)
            f.attrs["gravity"] = np.asarray(sim.gravity, np.float64)
            f.attrs["solver"] = sim.solver
            f.attrs["scene"] = sim.scene
            f.attrs["domain_min"] = np.asarray(sim.domain_min, np.float64)
            f.attrs["domain_max"] = np.asarray(sim.domain_max, np.float64)
            f.attrs["config"] = json.dumps(sim.config)
            comp = dict(compression="gzip", compression_opts=1) if sim.positions.size > 30000 else {}
            f.create_dataset("positions", data=sim.positions, **comp)
            f.create_dataset("velocities", data=sim.velocities, **comp)
            f.create_dataset("times", data=sim.times)
            if sim.source_index is not None:
                f.create_dataset("source_index", data=sim.source_index)
            g = f.create_group("stats")
            for k, v in sim.stats.items():
                g.create_dataset(k, data=np.asarray(v))
    return path


STAT_KEYS = ("density_err_mean", "density_err_max", "kinetic", "potential")


class SimWriter:
    """A ``sim.h5`` written frame by frame (``gf-cli simulate``): valid and readable after every
    frame, with ``complete = False`` until ``close(complete=True)``, so a crash or Ctrl-C at frame
    599 of 600 keeps 599 frames in a file that says it is incomplete."""

    def __init__(self, path, header: SimData, n_particles: int, frames_expected: int):
        self.path = Path(path)
        check_sim(header, str(self.path))
        h5py = _h5()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.f = h5py.File(self.path, "w")
        f = self.f
        f.attrs["format"] = SIM_FORMAT
        f.attrs["version"] = SIM_VERSION
        for k in ("fps", "particle_radius", "rest_density", "viscosity"):
            f.attrs[k] = float(getattr(header, k))
        f.attrs["gravity"] = np.asarray(header.gravity, np.float64)
        f.attrs["solver"] = header.solver
        f.attrs["scene"] = header.scene
        f.attrs["domain_min"] = np.asarray(header.domain_min, np.float64)
        f.attrs["domain_max"] = np.asarray(header.domain_max, np.float64)
        f.attrs["config"] = json.dumps(header.config)
        f.attrs["complete"] = False
        f.attrs["frames_expected"] = int(frames_expected)
        chunk = (1, n_particles, 3)
        for name in ("positions", "velocities"):
            f.create_dataset(name, shape=(0, n_particles, 3), maxshape=(None, n_particles, 3), dtype=np.float32,
                             chunks=chunk, compression="gzip" if n_particles * 3 > 30000 else None)
        f.create_dataset("times", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,))
        if header.source_index is not None:
            if header.source_index.shape != (n_particles,):
                raise InputError(str(self.path), f"source_index has {header.source_index.shape[0]} entries "
                                                 f"for {n_particles} particles")
            f.create_dataset("source_index", data=header.source_index)
        g = f.create_group("stats")
        for k in STAT_KEYS:
            g.create_dataset(k, shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,))
        f.flush()
        self.frames = 0

    @classmethod
    def reopen(cls, path, n_particles: int) -> "SimWriter | None":
        """A writer that goes on with an incomplete ``sim.h5`` of ``n_particles`` whose last frame
        carries the solver's resume state; None when the file is not one (complete, another
        size, no state, or unreadable), and the caller starts afresh."""
        h5py = _h5()
        try:
            f = h5py.File(path, "r+")
        except (OSError, ValueError):
            return None
        try:
            n = int(f["times"].shape[0])
            ok = (not bool(f.attrs.get("complete", True)) and n >= 1 and "resume_state" in f
                  and int(f["resume_state"].attrs.get("frame", -1)) == n - 1
                  and f["positions"].shape[1:] == (n_particles, 3)
                  and all(f[k].shape[0] >= n for k in ("positions", "velocities")))
        except (KeyError, OSError, ValueError, TypeError):
            ok = False
        if not ok:
            f.close()
            return None
        for name in ("positions", "velocities"):  # a frame torn by the kill, past the last complete one
            f[name].resize(n, axis=0)
        for name in STAT_KEYS:
            f["stats"][name].resize(n, axis=0)
        w = cls.__new__(cls)
        w.path, w.f, w.frames = Path(path), f, n
        return w

    def resume_state(self) -> tuple[np.ndarray, np.ndarray, dict]:
        """(positions, velocities) of the last frame written and the solver state saved with it."""
        f, k = self.f, self.frames - 1
        g = f["resume_state"]
        return (np.asarray(f["positions"][k]), np.asarray(f["velocities"][k]),
                {name: np.asarray(g[name]) for name in g})

    def append(self, positions, velocities, time: float, stats: dict | None = None,
               solver_state: dict | None = None) -> None:
        """Frame ``self.frames``; ``solver_state`` (arrays) is what a resumed run needs besides
        the frame, kept for the last frame only and dropped when the file is complete."""
        _check_finite("positions", np.asarray(positions), str(self.path))
        _check_finite("velocities", np.asarray(velocities), str(self.path))
        f, k = self.f, self.frames
        if "resume_state" in f:
            f["resume_state"].attrs["frame"] = -1  # until this frame is whole
        for name, a in (("positions", positions), ("velocities", velocities)):
            f[name].resize(k + 1, axis=0)
            f[name][k] = np.asarray(a, np.float32)
        f["times"].resize(k + 1, axis=0)
        f["times"][k] = float(time)
        for name in STAT_KEYS:
            d = f["stats"][name]
            d.resize(k + 1, axis=0)
            d[k] = float((stats or {}).get(name, np.nan))
        if solver_state is not None:
            g = f.require_group("resume_state")
            for name, a in solver_state.items():  # overwritten in place: HDF5 does not reuse freed space
                a = np.asarray(a)
                if name in g and (g[name].shape != a.shape or g[name].dtype != a.dtype):
                    del g[name]
                if name in g:
                    g[name][...] = a
                else:
                    g.create_dataset(name, data=a)
            for name in [n for n in g if n not in solver_state]:
                del g[name]
            g.attrs["frame"] = k
        self.frames = k + 1
        f.flush()

    def close(self, *, complete: bool, config: dict | None = None) -> Path:
        if self.f:
            if config is not None:
                self.f.attrs["config"] = json.dumps(config)
            self.f.attrs["complete"] = bool(complete)
            if complete and "resume_state" in self.f:
                del self.f["resume_state"]
            self.f.close()
            self.f = None
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(self.path, 0o666 & ~umask)
        return self.path


def read_sim(path) -> SimData:
    """Read and validate a ``sim.h5``; errors name the file and the problem."""
    with _open_checked(path, SIM_FORMAT, SIM_VERSION) as f:
        pos = _read(f, "positions", path, ndim=3, shape_tail=(3,))
        vel = _read(f, "velocities", path, ndim=3, shape_tail=(3,))
        if vel.shape != pos.shape:
            raise FormatError(path, f"velocities {vel.shape} do not match positions {pos.shape}")
        times = _read(f, "times", path, ndim=1, dtype=np.float64)
        if times.shape[0] != pos.shape[0]:
            raise FormatError(path, f"{times.shape[0]} times for {pos.shape[0]} frames")
        fps = _attr(f, "fps", path)
        radius = _attr(f, "particle_radius", path)
        if fps <= 0 or radius <= 0:
            raise FormatError(path, f"fps ({fps}) and particle_radius ({radius}) must be positive")
        gravity = _read_vec_attr(f, "gravity", path)
        dmin, dmax = _read_vec_attr(f, "domain_min", path), _read_vec_attr(f, "domain_max", path)
        if np.any(dmax <= dmin):
            raise FormatError(path, f"domain_max {dmax.tolist()} must exceed domain_min {dmin.tolist()}")
        stats = {k: np.asarray(v[()]) for k, v in f["stats"].items()} if "stats" in f else {}
        complete = f.attrs.get("complete", True)
        if np.ndim(complete) != 0 or not isinstance(complete.item() if hasattr(complete, "item") else complete,
                                                    (bool, int, np.bool_)):
            raise FormatError(path, f"attribute 'complete' must be true or false, got {short_repr(complete)}")
        complete = bool(complete)
        if pos.shape[0] == 0:
            raise FormatError(path, "holds no frames (the simulation stopped before its first frame)")
        src = None
        if "source_index" in f:
            src = _read(f, "source_index", path, ndim=1, dtype=np.int64)
            if src.shape[0] != pos.shape[1] or (src.size and src.min() < 0):
                raise FormatError(path, f"source_index must hold {pos.shape[1]} non-negative indices, "
                                        f"got {src.shape[0]} (min {src.min() if src.size else '-'})")
        return SimData(positions=pos, velocities=vel, fps=fps, particle_radius=radius,
                       rest_density=_attr(f, "rest_density", path),
                       viscosity=_attr(f, "viscosity", path), gravity=tuple(gravity.tolist()),
                       solver=_attr(f, "solver", path, str), domain_min=tuple(dmin.tolist()),
                       domain_max=tuple(dmax.tolist()), scene=_attr(f, "scene", path, str),
                       times=times, config=_json_attr(f, "config", path), stats=stats, complete=complete,
                       source_index=src)


def _read_vec_attr(f, name, path) -> np.ndarray:
    if name not in f.attrs:
        raise FormatError(path, f"missing attribute {name!r}")
    try:
        v = np.asarray(f.attrs[name], np.float64)
    except (TypeError, ValueError):
        v = None
    if v is None or v.shape != (3,) or not np.all(np.isfinite(v)):
        raise FormatError(path, f"attribute {name!r} must be 3 finite numbers, got {short_repr(f.attrs[name])}")
    return v


# ---- recon.h5 ------------------------------------------------------------------------------------
@dataclass
class DecoderData:
    """Weights of the time-continuous decoder Phi (paper Eq. 4) and its input encoding.

    layers: list of (weight (out, in), bias (out,)) as in ``torch.nn.Linear``; ReLU between layers.
    features: per-particle transform features theta, (N, N_theta).
    encoding: {"n_freqs": L, "include_input": bool} -- tau = [t, sin(2^k pi t), cos(2^k pi t)].
    outputs: ordered {name: width}, e.g. {"dp": 3, "ds": 3, "dr": 4}.
    """

    features: np.ndarray
    layers: list
    encoding: dict
    outputs: dict
    activation: str = "relu"
    residuals: np.ndarray | None = None       # (N, F, sum(outputs)): pose corrections at the knots (version 2)
    residual_knots: np.ndarray | None = None  # (F,) increasing tau of the knots
    color_residuals: np.ndarray | None = None  # (N, F, channels): degree-0 SH corrections at the knots (version 3)
    opacity_residuals: np.ndarray | None = None  # (N, F): logit-opacity corrections at the knots (version 3)


@dataclass
class ReconData:
    """A reconstruction: canonical Gaussian particles, optional decoder, time normalisation."""

    means: np.ndarray          # (N, 3)
    log_scales: np.ndarray     # (N, 3)
    quats: np.ndarray          # (N, 4) w, x, y, z (not necessarily normalised)
    logit_opacity: np.ndarray  # (N,)
    sh: np.ndarray             # (N, (degree+1)^2, channels)
    time_min: float = 0.0
    time_max: float = 1.0
    decoder: DecoderData | None = None
    config: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)

    @property
    def num_particles(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def channels(self) -> int:
        return self.sh.shape[2]


_CANONICAL = (("means", (3,)), ("log_scales", (3,)), ("quats", (4,)))


def _finite_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _numbers(v, n=None) -> bool:
    return isinstance(v, list) and (n is None or len(v) == n) and all(_finite_number(x) for x in v)


# The keys of recon.h5's ``config`` attribute that readers use (predict, evaluate, export, the
# Blender extension), each optional: name -> (test, what it must be)
RECON_CONFIG_SCHEMA = {
    "spacing": (lambda v: _finite_number(v) and v > 0, "a positive number (metres)"),
    "h": (lambda v: _finite_number(v) and v > 0, "a positive number (metres)"),
    "fluid_volume": (lambda v: _finite_number(v) and v > 0, "a positive number (cubic metres)"),
    "hull_volume": (lambda v: _finite_number(v) and v > 0, "a positive number (cubic metres)"),
    "canonical_time_s": (_finite_number, "a finite number (seconds)"),
    "fps": (lambda v: _finite_number(v) and v > 0, "a positive number or null"),
    "channels": (lambda v: v in (1, 3) and not isinstance(v, bool), "1 or 3"),
    "frame_times_s": (lambda v: _numbers(v) and all(b > a for a, b in zip(v, v[1:])),
                      "a list of increasing finite numbers (seconds)"),
    "time_policy": (lambda v: v in ("clamp", "error"), "'clamp' or 'error'"),
    "dataset": (lambda v: isinstance(v, str), "a path (a string)"),
    "dataset_options": (lambda v: isinstance(v, dict) and set(v) <= {"grayscale", "background_removal", "resolution",
                                                                       "downscale"},
                        "an object with grayscale, background_removal, resolution, downscale"),
    "bounds": (lambda v: isinstance(v, dict) and _numbers(v.get("lo"), 3) and _numbers(v.get("hi"), 3)
               and all(h > lo for lo, h in zip(v["lo"], v["hi"]))
               and all(_finite_number(v.get(k, 0.0)) for k in ("log_scale_min", "log_scale_max", "inset")),
               "{lo: [x, y, z], hi: [x, y, z]} with hi > lo, finite log_scale_min/max and inset"),
}


def _check_recon_config(cfg: dict, where) -> None:
    for key, (ok, what) in RECON_CONFIG_SCHEMA.items():
        if cfg.get(key) is not None and not ok(cfg[key]):
            raise FormatError(where, f"config key {key!r} must be {what}, got {short_repr(cfg[key])}")


def _check_recon(r: ReconData, where) -> None:
    _check_recon_config(r.config, where)
    n = r.means.shape[0] if r.means.ndim == 2 else -1
    for name, tail in _CANONICAL:
        a = getattr(r, name)
        if a.shape != (n,) + tail:
            raise FormatError(where, f"{name} must have shape ({n}, {tail[0]}), got {a.shape}")
    if r.logit_opacity.shape != (n,):
        raise FormatError(where, f"logit_opacity must have shape ({n},), got {r.logit_opacity.shape}")
    if r.sh.ndim != 3 or r.sh.shape[0] != n or r.sh.shape[2] not in (1, 3):
        raise FormatError(where, f"sh must have shape ({n}, (degree+1)^2, 1 or 3), got {r.sh.shape}")
    k = r.sh.shape[1]
    if k not in (1, 4, 9, 16):
        raise FormatError(where, f"sh has {k} coefficients per channel; expected 1, 4, 9 or 16 (degree 0-3)")
    if not (np.isfinite(r.time_min) and np.isfinite(r.time_max) and r.time_max > r.time_min):
        raise FormatError(where, f"time normalisation [{r.time_min}, {r.time_max}] is invalid")
    if r.decoder is not None:
        d = r.decoder
        if d.features.ndim != 2 or d.features.shape[0] != n:
            raise FormatError(where, f"decoder features must be ({n}, N_theta), got {d.features.shape}")
        if not d.layers:
            raise FormatError(where, "decoder has no layers")
        width = None
        for i, (w, b) in enumerate(d.layers):
            if w.ndim != 2 or b.shape != (w.shape[0],) or (width is not None and w.shape[1] != width):
                raise FormatError(where, f"decoder layer {i} has inconsistent shapes {w.shape}, {b.shape}")
            width = w.shape[0]
        if width != sum(d.outputs.values()):
            raise FormatError(where, f"decoder output width {width} != sum of outputs {d.outputs}")
        if (d.residuals is None) != (d.residual_knots is None):
            raise FormatError(where, "decoder residuals and residual_knots come together")
        if d.residuals is not None:
            kn = np.asarray(d.residual_knots)
            if kn.ndim != 1 or kn.size < 2 or not np.all(np.diff(kn) > 0) or not np.all(np.isfinite(kn)):
                raise FormatError(where, f"decoder residual_knots must be >= 2 increasing finite values, got {kn}")
            if np.shape(d.residuals) != (n, kn.size, width):
                raise FormatError(where, f"decoder residuals must have shape ({n}, {kn.size}, {width}), "
                                         f"got {np.shape(d.residuals)}")
            if not np.all(np.isfinite(d.residuals)):
                raise FormatError(where, "decoder residuals contain NaN or infinite values")
        for name, tail in (("color_residuals", (r.sh.shape[2],)), ("opacity_residuals", ())):
            a = getattr(d, name)
            if a is None:
                continue
            if d.residuals is None:
                raise FormatError(where, f"decoder {name} need the residuals (they share residual_knots)")
            want = (n, np.asarray(d.residual_knots).size) + tail
            if np.shape(a) != want:
                raise FormatError(where, f"decoder {name} must have shape {want}, got {np.shape(a)}")
            if not np.all(np.isfinite(a)):
                raise FormatError(where, f"decoder {name} contain NaN or infinite values")
    for name in ("means", "log_scales", "quats", "logit_opacity", "sh"):
        if not np.all(np.isfinite(getattr(r, name))):
            raise FormatError(where, f"{name} contains NaN or infinite values")
    # finite but beyond what float32 rendering survives: exp(log_scale) and squared distances overflow
    for name, limit, unit in (("means", 1e6, "metres"), ("log_scales", 30.0, "(log metres)")):
        big = float(np.abs(getattr(r, name)).max()) if getattr(r, name).size else 0.0
        if big > limit:
            raise FormatError(where, f"{name} reach {big:.3g} {unit}; more than {limit:g} is not a fluid scene")


def write_recon(path, r: ReconData) -> Path:
    path = Path(path)
    _check_recon(r, str(path))
    h5py = _h5()
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = RECON_FORMAT
            has_res = r.decoder is not None and r.decoder.residuals is not None
            looks = [k for k in ("color_residuals", "opacity_residuals")
                     if has_res and getattr(r.decoder, k) is not None]
            own = has_res and bool(r.decoder.encoding.get("canonical_residual", False))
            f.attrs["version"] = 4 if own else 3 if looks else (2 if has_res else 1)
            f.attrs["time_min"] = float(r.time_min)
            f.attrs["time_max"] = float(r.time_max)
            f.attrs["config"] = json.dumps(r.config)
            f.attrs["metrics"] = json.dumps(r.metrics)
            g = f.create_group("canonical")
            for name in ("means", "log_scales", "quats", "logit_opacity", "sh"):
                g.create_dataset(name, data=np.asarray(getattr(r, name), np.float32))
            g.attrs["sh_degree"] = r.sh_degree
            g.attrs["channels"] = r.channels
            if r.decoder is not None:
                d = f.create_group("decoder")
                d.create_dataset("features", data=np.asarray(r.decoder.features, np.float32))
                d.attrs["num_layers"] = len(r.decoder.layers)
                d.attrs["encoding"] = json.dumps(r.decoder.encoding)
                d.attrs["outputs"] = json.dumps(r.decoder.outputs)
                d.attrs["activation"] = r.decoder.activation
                for i, (w, b) in enumerate(r.decoder.layers):
                    d.create_dataset(f"layer{i}/weight", data=np.asarray(w, np.float32))
                    d.create_dataset(f"layer{i}/bias", data=np.asarray(b, np.float32))
                if has_res:
                    d.create_dataset("residuals", data=np.asarray(r.decoder.residuals, np.float32))
                    d.create_dataset("residual_knots", data=np.asarray(r.decoder.residual_knots, np.float64))
                for k in looks:
                    d.create_dataset(k, data=np.asarray(getattr(r.decoder, k), np.float32))
    return path


def read_recon(path) -> ReconData:
    with _open_checked(path, RECON_FORMAT, RECON_VERSIONS_READ) as f:
        version = int(f.attrs["version"])
        if "canonical" not in f:
            raise FormatError(path, "missing group 'canonical'")
        g = f["canonical"]
        arrays = {name: _read(g, name, path, finite=False)
                  for name in ("means", "log_scales", "quats", "logit_opacity", "sh")}
        decoder = None
        if "decoder" in f:
            d = f["decoder"]
            n_layers = _attr(d, "num_layers", path, int)
            layers = [(_read(d, f"layer{i}/weight", path, ndim=2), _read(d, f"layer{i}/bias", path, ndim=1))
                      for i in range(n_layers)]
            decoder = DecoderData(features=_read(d, "features", path, ndim=2), layers=layers,
                                  encoding=_json_attr(d, "encoding", path),
                                  outputs=_json_attr(d, "outputs", path),
                                  activation=_attr(d, "activation", path, str))
            if "residuals" in d:
                decoder.residuals = _read(d, "residuals", path, ndim=3)
                decoder.residual_knots = _read(d, "residual_knots", path, ndim=1, dtype=np.float64)
            if "color_residuals" in d:
                decoder.color_residuals = _read(d, "color_residuals", path, ndim=3)
            if "opacity_residuals" in d:
                decoder.opacity_residuals = _read(d, "opacity_residuals", path, ndim=2)
            if decoder.encoding.get("canonical_residual", False) and version < 4:
                raise FormatError(path, f"decoder encoding has canonical_residual, which needs version 4 (file: {version})")
        r = ReconData(**arrays, time_min=_attr(f, "time_min", path),
                      time_max=_attr(f, "time_max", path), decoder=decoder,
                      config=_json_attr(f, "config", path), metrics=_json_attr(f, "metrics", path))
    _check_recon(r, str(path))
    return r


# ---- grid.h5: a density field per frame (smoke ground truth) -------------------------------------------
@dataclass
class GridData:
    """A scalar density field per frame on a regular grid: ``density`` (F, nx, ny, nz) float32 >= 0,
    cell (i, j, k) centred at domain_min + (i + 0.5, j + 0.5, k + 0.5) * cell size, where the cell
    size is (domain_max - domain_min) / (nx, ny, nz); ``times`` (F,) seconds."""

    density: np.ndarray
    times: np.ndarray
    domain_min: tuple
    domain_max: tuple
    fps: float
    scene: str = ""
    config: dict = field(default_factory=dict)

    def __post_init__(self):
        self.density = np.asarray(self.density, np.float32)
        self.times = np.asarray(self.times, np.float64)
        if self.density.ndim != 4:
            raise InputError("grid data", f"density must be (frames, nx, ny, nz), got {self.density.shape}")
        if self.times.shape != (self.density.shape[0],):
            raise InputError("grid data", f"times must be ({self.density.shape[0]},), got {self.times.shape}")

    @property
    def cell(self) -> np.ndarray:
        return (np.asarray(self.domain_max, np.float64) - np.asarray(self.domain_min, np.float64)) \
            / np.asarray(self.density.shape[1:], np.float64)


def _check_grid(g: GridData, where) -> None:
    lo, hi = np.asarray(g.domain_min, np.float64), np.asarray(g.domain_max, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)) \
            or np.any(hi <= lo):
        raise FormatError(where, f"domain_min {short_repr(lo.tolist())} / domain_max {short_repr(hi.tolist())} "
                                 "must be 3 finite numbers each with max > min")
    if not (np.isfinite(g.fps) and g.fps > 0):
        raise FormatError(where, f"fps must be a positive number, got {g.fps}")
    if not np.all(np.isfinite(g.density)) or np.any(g.density < 0):
        raise FormatError(where, "density must be finite and >= 0 everywhere")
    if g.density.shape[0] > 1 and not np.all(np.diff(g.times) > 0):
        raise FormatError(where, "times must increase")


def write_grid(path, g: GridData) -> Path:
    """Write ``g`` to ``path`` atomically (gzip-compressed density). Refuses what ``read_grid`` refuses."""
    path = Path(path)
    _check_grid(g, str(path))
    h5py = _h5()
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = GRID_FORMAT
            f.attrs["version"] = GRID_VERSION
            f.attrs["fps"] = float(g.fps)
            f.attrs["scene"] = g.scene
            f.attrs["domain_min"] = np.asarray(g.domain_min, np.float64)
            f.attrs["domain_max"] = np.asarray(g.domain_max, np.float64)
            f.attrs["config"] = json.dumps(g.config)
            f.create_dataset("density", data=g.density, compression="gzip", compression_opts=1,
                             chunks=(1,) + g.density.shape[1:])
            f.create_dataset("times", data=g.times)
    return path


def read_grid(path) -> GridData:
    with _open_checked(path, GRID_FORMAT, GRID_VERSION) as f:
        density = _read(f, "density", path, ndim=4)
        times = _read(f, "times", path, ndim=1, dtype=np.float64)
        if times.shape != density.shape[:1]:
            raise FormatError(path, f"times has {times.shape[0]} entries for {density.shape[0]} density frames")
        g = GridData(density=density, times=times, domain_min=tuple(_read_vec_attr(f, "domain_min", path)),
                     domain_max=tuple(_read_vec_attr(f, "domain_max", path)), fps=_attr(f, "fps", path),
                     scene=_attr(f, "scene", path, cast=str) if "scene" in f.attrs else "",
                     config=_json_attr(f, "config", path))
    _check_grid(g, str(path))
    return g
