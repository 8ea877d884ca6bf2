"""Copy the training shapes into a compact ModelNet-layout folder, for a remote GPU machine.

    python training/pack_data.py OUT_DIR [--points 1024]

Writes OUT_DIR/modelnet10_hdf5_1024 (train split only) and OUT_DIR/modelnet40_subset_hdf5_2048
(train split, first ``--points`` points per shape: the pairs only ever use the first 1024) in
the same layout as ../shared/data (HDF5 shuffle + gzip 9). It exists because the device tool
carries at most 64 MiB, the working tree included. ``--decimals D`` stores coordinates with
HDF5's scale-offset filter at D decimal digits (h5py decodes it transparently): D = 4 changes
no coordinate by more than 1e-4 of the unit sphere (the pairs' noise has sigma 1e-2) and
halves the files (about 27 MiB for both); without it the copy is lossless (about 51 MiB).
ModelNet10's test split is deliberately left out: training never reads it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOLDERS = ("modelnet10_hdf5_1024", "modelnet40_subset_hdf5_2048")


def pack(out_dir: Path, points: int, decimals: int | None = None) -> None:
    for folder in FOLDERS:
        source, target = SHARED_DATA / folder, out_dir / folder
        target.mkdir(parents=True, exist_ok=True)
        (target / "shape_names.txt").write_text((source / "shape_names.txt").read_text())
        (target / "train_files.txt").write_text("ply_data_train0.h5\n")
        with (
            h5py.File(source / "ply_data_train0.h5", "r") as read,
            h5py.File(target / "ply_data_train0.h5", "w") as write,
        ):
            lossy = {} if decimals is None else {"scaleoffset": decimals}
            write.create_dataset(
                "data", data=read["data"][:, :points], shuffle=True, compression="gzip", compression_opts=9, **lossy
            )
            for key in ("label", "shape_name"):
                write.create_dataset(key, data=read[key][:])
        print(f"{target}: {(target / 'ply_data_train0.h5').stat().st_size / 2**20:.1f} MiB")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--points", type=int, default=1024)
    parser.add_argument("--decimals", type=int, default=None,
                        help="scale-offset filter digits (lossy; default lossless)")
    args = parser.parse_args()
    pack(args.out_dir, args.points, args.decimals)
