"""``drape info``: what this installation runs on (versions, devices, caches)."""
from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="versions of warp/torch/anny, devices found, kernel cache location",
                       description="Prints package versions, the Warp and torch devices found and where Warp caches kernels.")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)


def collect() -> dict:
    """Versions, devices and cache paths as a dict (also recorded in dataset provenance)."""
    def version(pkg: str) -> str | None:
        try:
            return importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            return None

    info = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "packages": {p: version(p) for p in ("drape", "warp-lang", "torch", "anny", "numpy", "h5py", "trimesh", "meshio", "ray", "newton")},
    }
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    info["warp_devices"] = [str(d) for d in wp.get_devices()]
    info["warp_kernel_cache"] = wp.config.kernel_cache_dir
    import torch

    info["torch_devices"] = ["cpu"] + [f"cuda:{i} ({torch.cuda.get_device_name(i)})" for i in range(torch.cuda.device_count())]
    info["anny_cache"] = os.path.join(os.path.expanduser("~"), ".cache", "anny")
    return info


def run(args: argparse.Namespace) -> int:
    info = collect()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print("drape installation")
    print(f"  python        {info['python']} on {info['platform']}")
    for pkg, ver in info["packages"].items():
        print(f"  {pkg:<13} {ver or '(not installed)'}")
    print(f"  warp devices  {', '.join(info['warp_devices'])}")
    print(f"  torch devices {', '.join(info['torch_devices'])}")
    print(f"  warp kernels  {info['warp_kernel_cache']}")
    print(f"  anny cache    {info['anny_cache']}")
    return 0
