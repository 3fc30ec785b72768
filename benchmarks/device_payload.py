"""Prepare what a lent GPU machine (the ``device`` tool) needs to run the training queue: ``.carry/`` (git-ignored).

    python benchmarks/device_payload.py [--root ../shared/data/modelnet40_mini] [--out .carry] [--no-wheels]
    python benchmarks/device_payload.py --unpack .carry --to ../shared/data   # on the device (device_chunk.sh)
    python benchmarks/device_payload.py --smoke     # pack and unpack a small generated folder (checks the script)
    python benchmarks/device_payload.py --slim lc_dcp_prnet_converge   # before the device calls, when over the limit
    python benchmarks/device_payload.py --unslim                       # after them, before any commit

The device receives the working tree (at most 64 MiB with the carried paths) and nothing beside it: not ``../shared``,
and its Python lacks jsonargparse. This writes

* ``<out>/<dataset>/``: the dataset folder, every file whole (the h5 arrays with their normals, which DVDs reads),
  each ``.h5`` file lzma-compressed to ``<name>.h5.xz`` (``modelnet40_mini``: 24 MB instead of 49 MB; its train
  file 19.6 MB, against 32.3 MB with gzip level 4 inside the h5), and ``MANIFEST.json`` with every file's size and
  SHA-256. Every compressed file is decompressed and checked against the source before the script ends;
* ``<out>/wheels/``: jsonargparse and its ``signatures`` extras at this environment's versions, for Python 3.12;

and prints the size of what would travel (tracked and untracked files not ignored, plus ``<out>``) against the limit.

``docs/results/`` outgrew that limit (73 MB tracked in session 34). ``--slim JOB ...`` takes it out of the git index
but for ``docs/results/converge/<JOB>`` (the finished rows that ``device_chunk.sh`` restores, so that the device does
not train them again) and names it in ``.git/info/exclude``: the working tree is untouched, only what travels
shrinks. ``--unslim`` puts the index back as ``HEAD`` has it (``git reset -- docs/results``) and drops the exclude
line. Between the two, ``git status`` shows ``docs/results`` as staged deletions, so ``--slim`` also installs a
``pre-commit`` hook that refuses every commit until ``--unslim`` removes it (``--slim`` refuses to run where the
repository has a ``pre-commit`` hook of its own).
On the device ``--unpack`` (standard library only) restores the folders under ``--to`` and checks each file's SHA-256
against the manifest, so the device trains on the same bytes as the developer machine. Then
``benchmarks/device_chunk.sh`` runs a queue job there (``device.run("bash benchmarks/device_chunk.sh <job>
<minutes>", carry=[".carry"])``; docs/reproducing.md).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import lzma
import shutil
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = "MANIFEST.json"
"""Written into each packed dataset folder: ``{file name: {"bytes": int, "sha256": str}}`` of the source files."""
COMPRESSED = (".h5",)
"""Suffixes of the files packed as ``<name>.xz``; every other file is copied as it is."""
LIMIT_BYTES = 64 * 2**20
"""What may travel to the device with one call (the ``device`` tool's limit)."""
WHEELS = ("jsonargparse", "docstring-parser", "typeshed-client")
"""Packages missing on the device image (``lcreg.cli`` needs ``jsonargparse[signatures]``)."""
RESULTS = "docs/results"
"""The tracked folder that ``--slim`` keeps from travelling, but for the named jobs' results in ``converge/``."""
SLIM_EXCLUDE = f"/{RESULTS}/"
"""The line ``--slim`` adds to ``.git/info/exclude`` (and ``--unslim`` removes)."""
SLIM_HOOK = f"""#!/bin/sh
# written by benchmarks/device_payload.py --slim, removed by --unslim
echo "{RESULTS} is out of the git index for a device call: run python benchmarks/device_payload.py --unslim" >&2
echo "before committing, or the commit deletes {RESULTS} from git" >&2
exit 1
"""
"""The ``pre-commit`` hook that :func:`slim_index` installs and :func:`unslim_index` removes."""
PLATFORM = ["--python-version", "3.12", "--implementation", "cp", "--platform", "manylinux2014_x86_64"]


class PayloadError(RuntimeError):
    """A packed file is missing from the manifest or its bytes differ from the source's."""


def sha256(path: Path) -> str:
    """The SHA-256 hex digest of the file ``path``."""
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(2**20), b""):
            digest.update(block)
    return digest.hexdigest()


def pack_dataset(root: Path, out: Path) -> int:
    """Pack the folder ``root`` into ``out`` (see the module docstring); returns the bytes written.

    Raises:
        PayloadError: If a compressed file does not decompress to the source's bytes.
    """
    out.mkdir(parents=True, exist_ok=True)
    manifest = {}
    for path in sorted(p for p in root.iterdir() if p.is_file()):
        manifest[path.name] = {"bytes": path.stat().st_size, "sha256": sha256(path)}
        if path.suffix in COMPRESSED:
            packed = out / f"{path.name}.xz"
            packed.write_bytes(lzma.compress(path.read_bytes(), preset=6))
            if hashlib.sha256(lzma.decompress(packed.read_bytes())).hexdigest() != manifest[path.name]["sha256"]:
                raise PayloadError(f"{packed} does not decompress to the bytes of {path}")
        else:
            shutil.copyfile(path, out / path.name)
    (out / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return sum(p.stat().st_size for p in out.iterdir())


def unpack_dataset(packed: Path, target: Path) -> list[Path]:
    """Restore the dataset folder ``packed`` (written by :func:`pack_dataset`) as ``target``; returns its files.

    Raises:
        PayloadError: If ``packed`` has no manifest, or a file is missing or differs from the manifest.
    """
    manifest_path = packed / MANIFEST
    if not manifest_path.is_file():
        raise PayloadError(f"{packed}: no {MANIFEST} (not written by device_payload.py)")
    target.mkdir(parents=True, exist_ok=True)
    restored = []
    for name, expected in json.loads(manifest_path.read_text()).items():
        source, dest = packed / name, target / name
        if (packed / f"{name}.xz").is_file():
            dest.write_bytes(lzma.decompress((packed / f"{name}.xz").read_bytes()))
        elif source.is_file():
            shutil.copyfile(source, dest)
        else:
            raise PayloadError(f"{packed}: {name!r} is in {MANIFEST} but neither it nor {name}.xz is there")
        if dest.stat().st_size != expected["bytes"] or sha256(dest) != expected["sha256"]:
            raise PayloadError(f"{dest}: its bytes differ from the source's ({MANIFEST} of {packed})")
        restored.append(dest)
    return restored


def unpack_all(carry: Path, to: Path) -> list[Path]:
    """:func:`unpack_dataset` for every packed folder (one with a manifest) in ``carry``, each into ``to/<name>``."""
    folders = sorted(p for p in carry.iterdir() if (p / MANIFEST).is_file())
    return [path for folder in folders for path in unpack_dataset(folder, to / folder.name)]


def _git(repo: Path, *args: str) -> str:
    """Run ``git -C repo args`` and return its standard output."""
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout


def travelling_bytes(repo: Path, carried: Path) -> int:
    """Bytes that one ``device`` call sends: ``repo``'s tracked and untracked-not-ignored files, plus ``carried``."""
    listing = _git(repo, "ls-files", "-z", "--cached", "--others", "--exclude-standard")
    files = [repo / name for name in listing.split("\0") if name]
    return sum(p.stat().st_size for p in files if p.is_file()) + sum(
        p.stat().st_size for p in carried.rglob("*") if p.is_file()
    )


def _git_path(repo: Path, name: str) -> Path:
    """``repo``'s ``.git/<name>`` (also from a worktree)."""
    path = Path(_git(repo, "rev-parse", "--git-path", name).strip())
    return path if path.is_absolute() else repo / path


def slim_index(repo: Path, keep: list[str]) -> None:
    """Keep :data:`RESULTS` from travelling but ``<RESULTS>/converge/<job>`` for each job of ``keep`` (see above),
    and refuse commits (:data:`SLIM_HOOK`) until :func:`unslim_index`.

    Raises:
        PayloadError: If a job of ``keep`` has no results folder, or ``repo`` has a ``pre-commit`` hook of its own.
    """
    missing = [job for job in keep if not (repo / RESULTS / "converge" / job).is_dir()]
    if missing:
        raise PayloadError(f"--slim: no {RESULTS}/converge/<job> folder for {', '.join(missing)}")
    hook = _git_path(repo, "hooks/pre-commit")
    if hook.exists() and hook.read_text(errors="replace") != SLIM_HOOK:
        raise PayloadError(f"--slim: {hook} is a pre-commit hook of its own; move it aside first")
    hook.parent.mkdir(parents=True, exist_ok=True)
    hook.write_text(SLIM_HOOK)
    hook.chmod(0o755)
    _git(repo, "rm", "-r", "-q", "--cached", "--ignore-unmatch", "--", RESULTS)
    if keep:
        _git(repo, "add", "-f", "--", *(f"{RESULTS}/converge/{job}" for job in keep))
    exclude = _git_path(repo, "info/exclude")
    lines = exclude.read_text().splitlines() if exclude.is_file() else []
    if SLIM_EXCLUDE not in lines:
        exclude.parent.mkdir(parents=True, exist_ok=True)
        exclude.write_text("\n".join([*lines, SLIM_EXCLUDE]) + "\n")


def unslim_index(repo: Path) -> None:
    """Undo :func:`slim_index`: :data:`RESULTS`'s index entries as ``HEAD`` has them, the exclude line and
    the commit guard gone (a ``pre-commit`` hook it did not write is left)."""
    _git(repo, "reset", "-q", "--", RESULTS)
    hook = _git_path(repo, "hooks/pre-commit")
    if hook.is_file() and hook.read_text(errors="replace") == SLIM_HOOK:
        hook.unlink()
    exclude = _git_path(repo, "info/exclude")
    if exclude.is_file():
        lines = [line for line in exclude.read_text().splitlines() if line != SLIM_EXCLUDE]
        exclude.write_text("".join(f"{line}\n" for line in lines))


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
    parser.add_argument("--unpack", type=Path, metavar="CARRY", help="restore the packed folders of CARRY (device)")
    parser.add_argument("--to", type=Path, default=ROOT.parent / "shared" / "data", help="where --unpack restores")
    parser.add_argument("--smoke", action="store_true", help="pack and unpack a small generated folder (temp folders)")
    parser.add_argument("--slim", nargs="*", metavar="JOB", help=f"keep {RESULTS} from travelling but these jobs'")
    parser.add_argument("--unslim", action="store_true", help="undo --slim (before any commit)")
    args = parser.parse_args(argv)
    if args.unslim:
        unslim_index(ROOT)
        print(f"{RESULTS}: index as HEAD has it; {SLIM_EXCLUDE} no longer excluded")
        return 0
    if args.slim is not None:
        slim_index(ROOT, args.slim)
        travels = travelling_bytes(ROOT, args.out)
        print(f"one device call sends {travels / 2**20:.1f} MiB of {LIMIT_BYTES / 2**20:.0f} MiB; run --unslim after")
        return 0 if travels <= LIMIT_BYTES else 1
    if args.unpack is not None:
        if not args.unpack.is_dir():
            parser.error(f"--unpack {str(args.unpack)!r} is not a folder (the .carry/ written by this script)")
        restored = unpack_all(args.unpack, args.to)
        print(f"{args.to}: {len(restored)} files restored, each checked against its {MANIFEST}")
        return 0
    if args.smoke:
        args.root, args.out, args.no_wheels = _smoke_folder(), Path(tempfile.mkdtemp(prefix="lcreg-payload-")), True
    if not args.root.is_dir():
        parser.error(f"--root {str(args.root)!r} is not a folder (ModelNet40, official h5 layout)")
    size = pack_dataset(args.root, args.out / args.root.name)
    print(f"{args.out / args.root.name}: {size / 1e6:.1f} MB (every file, h5 files lzma-compressed, checked)")
    if not args.no_wheels:
        print("\n".join(str(w) for w in download_wheels(args.out / "wheels")))
    if args.smoke:
        restored = unpack_all(args.out, args.out / "unpacked")
        print(f"{args.out / 'unpacked'}: {len(restored)} files restored and checked")
        return 0
    travels = travelling_bytes(ROOT, args.out)
    print(f"one device call sends {travels / 2**20:.1f} MiB of {LIMIT_BYTES / 2**20:.0f} MiB (tree + {args.out})")
    if travels > LIMIT_BYTES:
        print(f"over the limit: --slim <the chunk's jobs> keeps {RESULTS} but their results from travelling")
        return 1
    return 0


def _smoke_folder() -> Path:
    """A two-file h5 folder (with normals) in a temp folder."""
    import h5py
    import numpy as np

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
