"""geoloc-rs on the shared 7-Scenes frames: frames/s, per-stage medians, peak RSS, binary size.

Builds the map from frames 0–599 (every 3rd), exports test frames 600–699 with
geoloc.export_frames, runs ``geoloc-rs localize --stats`` sequentially (--threads 1) and with
the default threads, and prints the binary's size (and stripped size when ``strip`` exists).
Not a test. Run from the repository root after ``cargo build --release -p geoloc-cli``:

    PYTHONPATH=python python benchmarks/robot.py [--test 600:700] [--train-step 3] [--json FILE]

``--json`` writes the numbers (map build, export, each run's throughput, per-stage medians and
peak RSS as ``geoloc-rs --stats`` reports them, the binary's sizes); ``benchmarks/report.py``
renders them with their provenance.
"""

from __future__ import annotations

import argparse
import json
import re
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


def parse_stats(text: str) -> dict[str, object]:
    """The numbers of ``geoloc-rs localize --stats`` (its stderr summary)."""
    out: dict[str, object] = {}
    m = re.search(r"(\d+) frames in ([\d.]+) s \(([\d.]+) frames/s\); map loaded in ([\d.]+) s", text)
    if m:
        out.update(frames=int(m[1]), seconds=float(m[2]), frames_per_s=float(m[3]), map_load_s=float(m[4]))
    m = re.search(r"sources: (.*)", text)
    if m:
        out["sources"] = {k: int(v) for k, v in (item.rsplit(" ", 1) for item in m[1].split(", "))}
    m = re.search(r"median ms per stage: (.*)", text)
    if m:
        out["median_ms"] = {k: float(v) for k, v in (item.rsplit(" ", 1) for item in m[1].split(", "))}
    m = re.search(r"peak RSS: ([\d.]+) MiB", text)
    if m:
        out["peak_rss_mib"] = float(m[1])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--test", default="600:700", help="test frames A:B[:K]")
    parser.add_argument("--train-step", type=int, default=3)
    parser.add_argument("--json", type=Path, help="write the numbers here")
    args = parser.parse_args()
    result: dict[str, object] = {"test": args.test, "train_step": args.train_step, "runs": {}}
    a, b, *k = (int(x) for x in args.test.split(":"))
    seq = datasets.load_7scenes(REDKITCHEN)
    with tempfile.TemporaryDirectory() as tmp:
        map_path, frames = Path(tmp) / "kitchen.geoloc", Path(tmp) / "frames.bin"
        start = time.perf_counter()
        geoloc.Map.build(seq[0 : 600 : args.train_step]).save(map_path)
        built = {"keyframes": len(range(0, 600, args.train_step)), "build_s": time.perf_counter() - start,
                 "file_mib": map_path.stat().st_size / 2**20}
        result["map"] = built
        print(f"map: {built['keyframes']} keyframes in {built['build_s']:.1f} s, {built['file_mib']:.1f} MiB")
        start = time.perf_counter()
        n = geoloc.export_frames(geoloc.Map.load(map_path), seq[a : b : (k[0] if k else 1)], frames)
        exported = {"frames": n, "seconds": time.perf_counter() - start, "file_mib": frames.stat().st_size / 2**20}
        result["export"] = exported
        print(f"export_frames: {n} frames in {exported['seconds']:.1f} s, {exported['file_mib']:.1f} MiB")
        for threads in (["--threads", "1"], []):
            r = subprocess.run(
                [str(BINARY), "localize", "--map", str(map_path), "--input", str(frames), "--output", str(Path(tmp) / "p.txt"),
                 "--stats", *threads], capture_output=True, text=True, check=True,
            )
            name = " ".join(threads) or "default threads"
            result["runs"][name] = parse_stats(r.stderr)  # type: ignore[index]
            print(f"geoloc-rs localize {' '.join(threads) or '(default threads)'}:\n{r.stderr}")
    size = BINARY.stat().st_size
    result["binary_bytes"] = size
    print(f"binary: {size} bytes ({size / 2**20:.2f} MiB)")
    strip = shutil.which("strip")
    if strip is not None:
        with tempfile.TemporaryDirectory() as tmp:
            stripped = Path(tmp) / "geoloc-rs"
            subprocess.run([strip, "-o", str(stripped), str(BINARY)], check=True)
            stripped_bytes = stripped.stat().st_size
            result["stripped_bytes"] = stripped_bytes
            print(f"stripped: {stripped_bytes} bytes ({stripped_bytes / 2**20:.2f} MiB)")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
