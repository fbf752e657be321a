"""The native extension (C++/OpenMP for CPU tensors, CUDA for GPU tensors): one module,
``gf_native``, built on first use with ``torch.utils.cpp_extension`` and cached.

What is built: ``csrc/ext.cpp`` (one entry per op: checks, then CPU/CUDA dispatch; ``ops.h`` declares
them), the renderer's ``csrc/render/render_cpu.cpp`` and the SPH engine's ``csrc/sph/sph_cpu.cpp``
(neighbours, density) and ``csrc/sph/sim_cpu.cpp`` (the solvers' loops) and, when torch has CUDA and
``nvcc`` is found (``CUDA_HOME``, the PyPI wheel ``nvidia-cuda-nvcc``, or PATH),
``csrc/render/render_cuda.cu`` and ``csrc/sph/sph_cuda.cu`` with ``-DWITH_CUDA``. The Python side of
the ops lives with their users: ``render/native.py`` (projection, rasterisation) and ``sph/``
(K-nearest, density).

The build uses the ``ninja`` installed beside this Python (the project's venv), whatever PATH
says. The cache folder is keyed on everything that changes the binary: the sources' contents,
the flags, the C++ compiler's and nvcc's versions, torch's and Python's versions, for
``-march=native`` the CPU, and the sources' folder (two checkouts get a folder each). It lives
under ``$GF_EXT_DIR`` (default ``~/.cache/gaussfluids``).

If it cannot be built, ``available()`` is False, one warning says why (the compiler's own
first error lines; the whole log is kept in the build folder) and the renderer falls back to
the pure-torch reference. With ``GF_REQUIRE_NATIVE=1`` (set by ``make test`` and CI) a failed
build is an error instead: a broken native build cannot pass the test suite.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import torch

CSRC = Path(__file__).parent / "csrc"
CPU_SOURCES = ("ext.cpp", "render/render_cpu.cpp", "sph/sph_cpu.cpp", "sph/sim_cpu.cpp")
CUDA_SOURCES = ("render/render_cuda.cu", "sph/sph_cuda.cu")
HEADERS = ("ops.h", "parallel.h", "render/gaussian_math.h", "sph/sph_math.h")
INCLUDE_SUBDIRS = ("", "render", "sph")  # every header is included by its bare name
CXX_FLAGS = ["-O3", "-fopenmp", "-march=native"]
NVCC_FLAGS = ["-O3", "--use_fast_math", "-lineinfo", "--expt-relaxed-constexpr"]
_ext = None
_error: str | None = None
_cuda_note: str | None = None


def required() -> bool:
    return os.environ.get("GF_REQUIRE_NATIVE", "") not in ("", "0")


def _tool_dirs() -> list[str]:
    """Folders holding the ninja this Python installed (venv bin, the ninja package's bin)."""
    dirs = [str(Path(sys.executable).parent)]
    try:
        import ninja  # the PyPI package ships the binary

        dirs.append(str(Path(ninja.BIN_DIR)))
    except (ImportError, AttributeError):
        pass
    return [d for d in dirs if Path(d, "ninja").exists() or Path(d, "ninja.exe").exists()]


def _version(cmd: list[str]) -> str:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.strip().splitlines()[0]
    except (OSError, IndexError, subprocess.SubprocessError):
        return "unknown"


def find_cuda_home() -> str | None:
    """CUDA_HOME, else the nvcc of the PyPI wheels (nvidia/cu13 or nvidia/cuda_nvcc), else PATH's."""
    env = os.environ.get("CUDA_HOME") or os.environ.get("CUDA_PATH")
    if env and Path(env, "bin", "nvcc").exists():
        return env
    try:
        import nvidia

        for base in nvidia.__path__:
            for sub in ("cu13", "cu12", "cuda_nvcc"):
                if Path(base, sub, "bin", "nvcc").exists():
                    return str(Path(base, sub))
    except ImportError:
        pass
    nvcc = shutil.which("nvcc")
    return str(Path(nvcc).resolve().parent.parent) if nvcc else None


def prepare_cuda_home(home: str) -> None:
    """The wheels ship libcudart.so.13 but no unversioned libcudart.so, which the linker wants."""
    lib = Path(home, "lib")
    if lib.exists() and not (lib / "libcudart.so").exists():
        versioned = sorted(lib.glob("libcudart.so.*"))
        if versioned:
            try:
                (lib / "libcudart.so").symlink_to(versioned[0].name)
            except OSError:
                pass


def _want_cuda() -> tuple[bool, str | None]:
    global _cuda_note
    if os.environ.get("GF_NO_CUDA", "") not in ("", "0"):
        return False, None
    if not torch.cuda.is_available():
        return False, None
    home = find_cuda_home()
    if home is None:
        _cuda_note = "torch sees a GPU but no nvcc was found (set CUDA_HOME); CUDA tensors use the reference backend"
        return False, None
    return True, home


def _build_dir(with_cuda: bool, cuda_home: str | None) -> Path:
    h = hashlib.sha1()
    for name in CPU_SOURCES + HEADERS + (CUDA_SOURCES if with_cuda else ()):
        h.update(name.encode())
        h.update((CSRC / name).read_bytes())
    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:  # -march=native code is tied to the CPU
            cpu = "".join(line for line in f if line.startswith(("model name", "flags")))[:4000]
    except OSError:
        cpu = platform.processor()
    cxx = os.environ.get("CXX", "c++")
    # the sources' folder too: ninja's build file names the sources by path, so two checkouts that
    # shared a folder would rebuild it in turn, each for its own paths
    parts = [cpu, torch.__version__, platform.python_version(), " ".join(CXX_FLAGS), _version([cxx, "--version"]),
             str(CSRC.resolve())]
    if with_cuda:
        parts += [" ".join(NVCC_FLAGS), _version([str(Path(cuda_home, "bin", "nvcc")), "--version"]),
                  torch.version.cuda or "", str(torch.cuda.get_device_capability(0))]
    h.update("|".join(parts).encode())
    root = Path(os.environ.get("GF_EXT_DIR", Path.home() / ".cache" / "gaussfluids"))
    d = root / f"{'cuda' if with_cuda else 'cpu'}-{h.hexdigest()[:12]}"
    d.mkdir(parents=True, exist_ok=True)
    return d


def compiler_errors(log: str, limit: int = 25) -> str:
    """The compiler's own diagnostics from a build log (not the command lines)."""
    lines = log.splitlines()
    keep = []
    for k, ln in enumerate(lines):
        low = ln.lower()
        if ("error" in low or "fatal" in low) and not ln.lstrip().startswith(("[", "FAILED:", "c++ ", "g++ ",
                                                                              "/usr/bin/", "nvcc ")) \
                and len(ln) < 600:
            keep.extend(lines[k:k + 3])
        if len(keep) >= limit:
            break
    return "\n".join(keep[:limit]) if keep else "\n".join(lines[-limit:])


def load():
    """The compiled extension module, or None (with one warning) if it cannot be built."""
    global _ext, _error
    if _ext is not None or _error is not None:
        return _ext
    if os.environ.get("GF_NO_NATIVE", "") not in ("", "0"):
        _error = "disabled by GF_NO_NATIVE"
        if required():
            raise RuntimeError("GF_REQUIRE_NATIVE and GF_NO_NATIVE are both set")
        return None
    with_cuda, cuda_home = _want_cuda()
    build_dir = _build_dir(with_cuda, cuda_home)
    old_path, old_home = os.environ.get("PATH", ""), os.environ.get("CUDA_HOME")
    try:
        from torch.utils import cpp_extension

        os.environ["PATH"] = os.pathsep.join(_tool_dirs() + [old_path])
        sources = [str(CSRC / s) for s in CPU_SOURCES]
        kw = {}
        if with_cuda:
            prepare_cuda_home(cuda_home)
            os.environ["CUDA_HOME"] = cuda_home
            cpp_extension.CUDA_HOME = cuda_home
            sources += [str(CSRC / s) for s in CUDA_SOURCES]
            kw = dict(extra_cuda_cflags=NVCC_FLAGS + ["-DWITH_CUDA"], with_cuda=True)
        _ext = cpp_extension.load(
            name="gf_native", sources=sources, extra_include_paths=[str(CSRC / d) for d in INCLUDE_SUBDIRS],
            extra_cflags=CXX_FLAGS + (["-DWITH_CUDA"] if with_cuda else []), extra_ldflags=["-fopenmp"],
            build_directory=str(build_dir), verbose=os.environ.get("GF_NATIVE_VERBOSE", "") not in ("", "0"), **kw)
    except Exception as e:  # noqa: BLE001 - no compiler, a compile error, ...: fall back or fail loudly
        log = str(e)
        (build_dir / "build_error.log").write_text(log)
        _error = (f"{type(e).__name__} building {'CPU+CUDA' if with_cuda else 'CPU'} ops; compiler said:\n"
                  f"{compiler_errors(log)}\n(full log: {build_dir / 'build_error.log'})")
        _ext = None
        if required():
            raise RuntimeError(f"the native extension must build here (GF_REQUIRE_NATIVE=1) but did not: {_error}") from None
        warnings.warn(f"gaussfluids: native extension unavailable ({_error}); using the pure-torch reference "
                      "backend, which is much slower", RuntimeWarning, stacklevel=3)
    finally:
        os.environ["PATH"] = old_path
        if old_home is None:
            os.environ.pop("CUDA_HOME", None)
        else:
            os.environ["CUDA_HOME"] = old_home
    if _cuda_note:
        warnings.warn(f"gaussfluids: {_cuda_note}", RuntimeWarning, stacklevel=3)
    return _ext


def available() -> bool:
    return load() is not None


def has_cuda() -> bool:
    return available() and bool(_ext.has_cuda())


def unavailable_reason() -> str | None:
    load()
    return _error


def compile_cuda_sources(out_dir, *, arch: str = "sm_90") -> list[dict]:
    """Compile every ``csrc/**/*.cu`` to an object file with nvcc (no GPU needed; nvcc from CUDA_HOME
    or the PyPI wheels): the check CI runs so that a CUDA syntax error never lands unseen.
    Returns one record per file: {file, ok, seconds, log}."""
    import sysconfig
    import time

    from torch.utils.cpp_extension import include_paths

    home = find_cuda_home()
    if home is None:
        raise RuntimeError("no nvcc found: install the nvidia-cuda-nvcc, nvidia-cuda-crt and nvidia-nvvm wheels "
                           "(pip install '.[cuda-build]') or set CUDA_HOME")
    nvcc = str(Path(home, "bin", "nvcc"))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    incs = [str(CSRC / d) for d in INCLUDE_SUBDIRS] + [sysconfig.get_paths()["include"], str(Path(home, "include"))] + include_paths()
    abi = int(torch._C._GLIBCXX_USE_CXX11_ABI)
    recs = []
    for name in sorted(p.relative_to(CSRC).as_posix() for p in CSRC.rglob("*.cu")):
        cmd = [nvcc, "-c", str(CSRC / name), "-o", str(out_dir / (Path(name).name + ".o")), "-std=c++20", f"-arch={arch}",
               "-DWITH_CUDA", "-DTORCH_EXTENSION_NAME=gf_native", f"-D_GLIBCXX_USE_CXX11_ABI={abi}",
               "-Xcompiler", "-fPIC", *NVCC_FLAGS] + [f"-I{i}" for i in incs]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True,
                              env=dict(os.environ, PATH=os.pathsep.join(_tool_dirs() + [os.environ.get("PATH", "")])))
        recs.append({"file": name, "ok": proc.returncode == 0, "seconds": time.perf_counter() - t0,
                     "log": (proc.stdout + proc.stderr)[-20000:]})
    return recs
