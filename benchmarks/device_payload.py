"""Prepare what a lent GPU machine (the ``device`` tool) needs to run the training queue: ``.carry/`` (git-ignored).

    python benchmarks/device_payload.py [--root ../shared/data/modelnet40_mini] [--out .carry] [--no-wheels]
    python benchmarks/device_payload.py --smoke     # the data step on the embedded test files (checks the script)

The device receives the working tree (at most 64 MiB with the carried paths) and nothing beside it: not ``../shared``,
and its Python lacks jsonargparse. This writes

* ``<out>/modelnet40_mini/``: the ModelNet40 folder with only the ``data`` and ``label`` arrays, gzip-compressed
  (20 MB instead of 49 MB; the tracked files are about 27 MB). The ``normal`` arrays are dropped: DCP-v2, PRNet,
  IDAM, DeepGMR, PointNetLK, PCRNet and FMR-Net never read them, DVDs does (its GPU jobs need the full files). Every
  array written is read back and compared with the source, bit for bit;
* ``<out>/wheels/``: jsonargparse and its ``signatures`` extras at this environment's versions, for Python 3.12.

Then ``benchmarks/device_chunk.sh`` runs a queue job there (``device.run("bash benchmarks/device_chunk.sh <job>
<minutes>", carry=[".carry"])``; docs/reproducing.md).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KEPT = ("data", "label")
"""The h5 arrays the device's jobs read."""
WHEELS = ("jsonargparse", "docstring-parser", "typeshed-client")
"""Packages missing on the device image (``lcreg.cli`` needs ``jsonargparse[signatures]``)."""
PLATFORM = ["--python-version", "3.12", "--implementation", "cp", "--platform", "manylinux2014_x86_64"]


def strip_h5(source: Path, target: Path) -> int:
    """Copy ``source`` to ``target`` keeping :data:`KEPT` (gzip level 4); returns the bytes written.

    Raises:
        RuntimeError: If an array read back from ``target`` differs from the source's.
    """
    with h5py.File(source, "r") as src, h5py.File(target, "w") as dst:
        for key in KEPT:
            dst.create_dataset(key, data=src[key][...], compression="gzip", compression_opts=4)
    with h5py.File(source, "r") as src, h5py.File(target, "r") as dst:
        for key in KEPT:
            if not np.array_equal(src[key][...], dst[key][...]):
                raise RuntimeError(f"{target}: {key!r} differs from {source} after the copy")
    return target.stat().st_size


def copy_dataset(root: Path, out: Path) -> int:
    """Copy the folder ``root`` into ``out`` (h5 files stripped by :func:`strip_h5`); returns the bytes written."""
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for path in sorted(root.iterdir()):
        if path.suffix == ".h5":
            written += strip_h5(path, out / path.name)
        elif path.is_file():
            written += Path(shutil.copy2(path, out / path.name)).stat().st_size
    return written


def download_wheels(out: Path) -> list[Path]:
    """``pip download`` :data:`WHEELS` at this environment's versions (pure Python wheels) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    pins = [f"{name}=={metadata.version(name)}" for name in WHEELS]
    pip = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", *PLATFORM]
    subprocess.run([*pip, "-d", str(out), *pins], check=True)
    return sorted(out.glob("*.whl"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, default=ROOT.parent / "shared" / "data" / "modelnet40_mini")
    parser.add_argument("--out", type=Path, default=ROOT / ".carry")
    parser.add_argument("--no-wheels", action="store_true", help="only the data")
    parser.add_argument("--smoke", action="store_true", help="strip a small generated h5 folder into a temp folder")
    args = parser.parse_args(argv)
    if args.smoke:
        args.root, args.out, args.no_wheels = _smoke_folder(), Path(tempfile.mkdtemp(prefix="lcreg-payload-")), True
    if not args.root.is_dir():
        parser.error(f"--root {str(args.root)!r} is not a folder (ModelNet40, official h5 layout)")
    size = copy_dataset(args.root, args.out / args.root.name)
    print(f"{args.out / args.root.name}: {size / 1e6:.1f} MB ({', '.join(KEPT)} of every h5 file, checked equal)")
    if not args.no_wheels:
        print("\n".join(str(w) for w in download_wheels(args.out / "wheels")))
    return 0


def _smoke_folder() -> Path:
    """A two-file h5 folder (with normals) in a temp folder."""
    folder = Path(tempfile.mkdtemp(prefix="lcreg-payload-src-"))
    rng = np.random.default_rng(0)
    for name in ("ply_data_train0.h5", "ply_data_test0.h5"):
        with h5py.File(folder / name, "w") as f:
            f["data"] = rng.standard_normal((3, 64, 3)).astype(np.float32)
            f["normal"] = rng.standard_normal((3, 64, 3)).astype(np.float32)
            f["label"] = np.arange(3, dtype=np.uint8)[:, None]
    (folder / "train_files.txt").write_text("data/modelnet40_ply_hdf5_2048/ply_data_train0.h5\n")
    (folder / "test_files.txt").write_text("data/modelnet40_ply_hdf5_2048/ply_data_test0.h5\n")
    return folder


if __name__ == "__main__":
    raise SystemExit(main())
