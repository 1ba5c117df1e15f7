"""geoloc-rs on the shared 7-Scenes frames: frames/s, per-stage medians, peak RSS, binary size.

Builds the map from frames 0–599 (every 3rd), exports test frames 600–699 with
geoloc.export_frames, runs ``geoloc-rs localize --stats`` sequentially (--threads 1) and with
the default threads, and prints the binary's size (and stripped size when ``strip`` exists).
Not a test. Run from the repository root after ``cargo build --release -p geoloc-cli``:

    PYTHONPATH=python python benchmarks/robot.py [--test 600:700] [--train-step 3]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import geoloc
from geoloc import datasets

ROOT = Path(__file__).resolve().parents[1]
BINARY = ROOT / "target" / "release" / "geoloc-rs"
REDKITCHEN = ROOT.parent / "shared" / "data" / "7scenes-redkitchen"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--test", default="600:700", help="test frames A:B[:K]")
    parser.add_argument("--train-step", type=int, default=3)
    args = parser.parse_args()
    a, b, *k = (int(x) for x in args.test.split(":"))
    seq = datasets.load_7scenes(REDKITCHEN)
    with tempfile.TemporaryDirectory() as tmp:
        map_path, frames = Path(tmp) / "kitchen.geoloc", Path(tmp) / "frames.bin"
        start = time.perf_counter()
        geoloc.Map.build(seq[0 : 600 : args.train_step]).save(map_path)
        print(f"map: {len(range(0, 600, args.train_step))} keyframes in {time.perf_counter() - start:.1f} s, "
              f"{map_path.stat().st_size / 2**20:.1f} MiB")
        start = time.perf_counter()
        n = geoloc.export_frames(geoloc.Map.load(map_path), seq[a : b : (k[0] if k else 1)], frames)
        print(f"export_frames: {n} frames in {time.perf_counter() - start:.1f} s, {frames.stat().st_size / 2**20:.1f} MiB")
        for threads in (["--threads", "1"], []):
            r = subprocess.run(
                [str(BINARY), "localize", "--map", str(map_path), "--input", str(frames), "--output", str(Path(tmp) / "p.txt"),
                 "--stats", *threads], capture_output=True, text=True, check=True,
            )
            print(f"geoloc-rs localize {' '.join(threads) or '(default threads)'}:\n{r.stderr}")
    size = BINARY.stat().st_size
    print(f"binary: {size} bytes ({size / 2**20:.2f} MiB)")
    strip = shutil.which("strip")
    if strip is not None:
        with tempfile.TemporaryDirectory() as tmp:
            stripped = Path(tmp) / "geoloc-rs"
            subprocess.run([strip, "-o", str(stripped), str(BINARY)], check=True)
            print(f"stripped: {stripped.stat().st_size} bytes ({stripped.stat().st_size / 2**20:.2f} MiB)")


if __name__ == "__main__":
    main()
