"""Seed 001's whole-image decoder alone: inference ms per frame at each batch size and one
training step (forward, masked L1, backward, Adam) per batch; prints one JSON line each.

The decoder is what seed 001 times; the full UV-image forward also poses the body and
samples the images (see ``drape evaluate``'s ``ms_per_frame_batch_*``).

    python bench/bench_uvimage_decoder.py [--device cuda] [--batches 1 32] [--repeats 50]
"""
from __future__ import annotations

import argparse
import json
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 32])
    parser.add_argument("--train-batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--size", type=int, default=256)
    args = parser.parse_args()
    import torch

    from learn.uvimage.decoder import ImageDecoder

    device = torch.device(args.device)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    torch.manual_seed(0)
    decoder = ImageDecoder(90, 6, size=args.size).to(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    decoder.eval()
    with torch.no_grad():
        for batch in args.batches:
            x = torch.randn(batch, 90, device=device)
            for _ in range(5):
                decoder(x)
            sync()
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                decoder(x)
                sync()
                times.append(time.perf_counter() - start)
            times.sort()
            print(json.dumps({"bench": "uvimage_decoder_inference", "device": name, "batch": batch,
                              "ms_per_frame": 1e3 * times[len(times) // 2] / batch,
                              "parameters": sum(p.numel() for p in decoder.parameters())}))
    decoder.train()
    optimizer = torch.optim.Adam(decoder.parameters(), lr=1e-3)
    x = torch.randn(args.train_batch, 90, device=device)
    target = torch.randn(args.train_batch, 6, args.size, args.size, device=device) * 0.01
    mask = (torch.rand(2, args.size, args.size, device=device) > 0.5).float()
    times = []
    for step in range(args.repeats + 5):
        start = time.perf_counter()
        diff = (decoder(x) - target).abs().reshape(args.train_batch, 2, 3, args.size, args.size).sum(2)
        loss = (diff * mask).sum() / (mask.sum() * args.train_batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        sync()
        if step >= 5:
            times.append(time.perf_counter() - start)
    times.sort()
    print(json.dumps({"bench": "uvimage_decoder_train_step", "device": name, "batch": args.train_batch,
                      "ms_per_step": 1e3 * times[len(times) // 2]}))


if __name__ == "__main__":
    main()
