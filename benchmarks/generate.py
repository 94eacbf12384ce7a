"""Generation speed: videos per second, simulated, rendered and written to HDF5.

    python benchmarks/generate.py [--videos 4000] [--pairs 200] [--size 64] [--workers 2]

Prints train and test throughput with the given workers and, as the baseline run in the
same process, with one worker; the last line holds the figures to record.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from xvoe.generate import GenerateConfig, generate


def throughput(config: GenerateConfig, workers: int, folder: Path) -> float:
    out = folder / f"{config.split}-{workers}.h5"
    start = time.perf_counter()
    generate(config, out, workers=workers, overwrite=True, progress=False)
    seconds = time.perf_counter() - start
    videos = config.units * config.videos_per_unit
    print(f"{config.split:5s} workers={workers} videos={videos} seconds={seconds:.2f} "
          f"videos/s={videos / seconds:.0f} file={out.stat().st_size / 2**20:.1f} MiB")
    return videos / seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--videos", type=int, default=4000)
    parser.add_argument("--pairs", type=int, default=200, help="test pairs per setting")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    train = GenerateConfig("train", videos=args.videos, size=args.size, seed=0)
    test = GenerateConfig("test", pairs=args.pairs, size=args.size, seed=1)
    with tempfile.TemporaryDirectory() as folder:
        results = {}
        for config in (train, test):
            base = throughput(config, 1, Path(folder))
            fast = throughput(config, args.workers, Path(folder))
            results[config.split] = (fast, fast / base)
    print(" ".join(f"{split}_videos_per_s={v:.0f} {split}_speedup_vs_1_worker={r:.2f}"
                   for split, (v, r) in results.items()))


if __name__ == "__main__":
    main()
