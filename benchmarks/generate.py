"""Generation speed: videos per second, simulated, rendered and written to HDF5.

    python benchmarks/generate.py [--videos 4000] [--pairs 200] [--size 64] [--workers 2]

Prints train and test throughput with the given workers and, as the baseline run in the
same process, with one worker; the last line holds the figures to record. It also prints the
CPU time per video (this process and its workers), which other load on the machine does not
inflate: 2000 / cpu_ms_per_video is what two idle cores can do.
"""
from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import xvoe


def cpu_seconds() -> float:
    """CPU time of this process and of its finished workers."""
    own, workers = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + workers.ru_utime + workers.ru_stime


def throughput(config: xvoe.GenerateConfig, workers: int, folder: Path) -> float:
    out = folder / f"{config.split}-{workers}.h5"
    start, cpu_start = time.perf_counter(), cpu_seconds()
    xvoe.generate(config, out, workers=workers, overwrite=True, progress=False)
    seconds, cpu = time.perf_counter() - start, cpu_seconds() - cpu_start
    videos = config.units * config.videos_per_unit
    print(f"{config.split:5s} workers={workers} videos={videos} seconds={seconds:.2f} "
          f"videos/s={videos / seconds:.0f} cpu_ms_per_video={1000 * cpu / videos:.2f} "
          f"file={out.stat().st_size / 2**20:.1f} MiB")
    return videos / seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--videos", type=int, default=4000)
    parser.add_argument("--pairs", type=int, default=200, help="test pairs per setting")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    train = xvoe.GenerateConfig("train", videos=args.videos, size=args.size, seed=0)
    test = xvoe.GenerateConfig("test", pairs=args.pairs, size=args.size, seed=1)
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
