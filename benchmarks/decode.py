"""Decoding many latents at once against in chunks (ComponentVAE.decode), in one process.

The NLL decodes particles x frames latents per video and MSE scoring slots x frames per
batch; this measures the chunk size `ComponentVAE.DECODE_CHUNK` was chosen by.

    python benchmarks/decode.py [--model xpl] [--latents 960] [--threads 2]

Last line: whole_ms=N.N chunked_ms=N.N ratio=N.NN (chunks of DECODE_CHUNK)
"""
from __future__ import annotations

import argparse
import time

import torch

from xvoe.evaluation.score import load_model


def per_call_ms(decode, z: torch.Tensor, repeats: int) -> float:
    decode(z)
    start = time.perf_counter()
    for _ in range(repeats):
        decode(z)
    return (time.perf_counter() - start) / repeats * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="xpl")
    parser.add_argument("--latents", type=int, default=960, help="latents per call (64 particles x 15 frames)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    vae = load_model(args.model).vae
    z = torch.randn(args.latents, vae.config.latent_dim, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        whole_ms = per_call_ms(vae.decoder, z, args.repeats)
        for size in (16, 32, 64, 128, 256):
            ms = per_call_ms(lambda x, size=size: torch.cat([vae.decoder(c) for c in x.split(size)]), z, args.repeats)
            print(f"chunks of {size:4d}: {ms:7.1f} ms  ratio to whole {whole_ms / ms:.2f}")
        chunked_ms = per_call_ms(vae.decode, z, args.repeats)
        diff = (vae.decode(z) - vae.decoder(z)).abs().max().item()
    print(f"{args.latents} latents, {args.threads} threads, max_diff={diff:.1e}")
    print(f"whole_ms={whole_ms:.1f} chunked_ms={chunked_ms:.1f} ratio={whole_ms / chunked_ms:.2f} "
          f"(chunks of {vae.DECODE_CHUNK})")


if __name__ == "__main__":
    main()
