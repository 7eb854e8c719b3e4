"""The device streams of the frame loop (CUDA): frames step on a stream of their own."""
from __future__ import annotations

from contextlib import contextmanager

import torch


class FrameStreams:
    """Where the frame loop's device work goes. On CUDA the simulator's frames run on a stream of
    their own that does not synchronize with the CUDA default stream, which torch uses (body
    posing, inverse skinning): host work between frames then runs beside a frame in flight
    instead of waiting behind it, and ``delivering`` puts the frame callback's Warp work (the
    quality filters) on the stream that was current when the loop began, which does not wait for
    the frame either. Everything that touches the simulator's or the collider's state stays on the
    stepping stream, so it is ordered after the frame in flight. On the CPU both contexts do nothing
    (Warp's CPU launches run to completion)."""

    def __init__(self, device: str, *, enabled: bool = True) -> None:
        import warp as wp

        self._wp = wp
        dev = wp.get_device(device)
        self.enabled = bool(enabled and dev.is_cuda and torch.cuda.is_available())
        if self.enabled:
            self._torch_stream = torch.cuda.Stream(device=torch.device("cuda", dev.ordinal))  # non-blocking
            self.step_stream = wp.stream_from_torch(self._torch_stream)
            self.deliver_stream = dev.stream

    @contextmanager
    def stepping(self):
        """The frame loop: the stepping stream is current (it first waits for the work queued
        before on the device's stream) and, on leaving, the host waits for it."""
        if not self.enabled:
            yield
            return
        wp = self._wp
        with wp.ScopedStream(self.step_stream):
            try:
                yield
            finally:
                wp.synchronize_stream(self.step_stream)

    @contextmanager
    def delivering(self):
        """Frame callbacks: Warp work goes to the delivery stream, not behind the frame in flight
        (the callback gets host arrays; nothing of it depends on the stepping stream)."""
        if not self.enabled:
            yield
            return
        with self._wp.ScopedStream(self.deliver_stream, sync_enter=False):
            yield
