"""Copies of torch CUDA tensors into Warp arrays without a host round trip.

The sequence driver poses bodies with torch on the GPU and steps the cloth with Warp on a stream
of its own; a tensor handed to Warp must be finished on torch's stream first, and must outlive
the copy before it goes back to torch's allocator. :func:`copy_cuda_tensor` does both.
"""

from __future__ import annotations

import warp as wp

__all__ = ["copy_cuda_tensor"]


def copy_cuda_tensor(dst: wp.array, src, dtype=wp.vec3) -> None:
    """Copy the CUDA tensor ``src`` into the Warp array ``dst`` (same device, same element count).

    Args:
        dst: Warp array on a CUDA device, ``dtype`` elements (N,).
        src: torch tensor on that device, (N, 3) for vec3 (any float dtype: cast to float32).
        dtype: the Warp element type ``src`` is viewed as.
    """
    import torch

    src = src.detach().reshape(len(dst), -1).to(torch.float32).contiguous()
    # torch's work on the tensor is finished first; the copy is finished before ``src`` is freed
    torch.cuda.current_stream(src.device).synchronize()
    wp.copy(dst, wp.from_torch(src, dtype=dtype))
    wp.synchronize_stream(wp.get_stream(dst.device))
