"""TailorNet (seed 000) and its baseline, in torch.

``lf`` (displacement MLPs, low-frequency model), ``hf`` (K stacked prototype pose
models), ``shape_style`` (g: canonical garment), ``mixture`` (kernel weights), ``model``
(:class:`TailorNet`), ``baseline``, ``pose_mask``, ``train`` (resumable stages,
checkpoints, fingerprints), ``evaluate`` (metrics, timing). The greedy prototype choice
(Sec. 4.4) is ``simulate.garment.prototypes``: the style space picks prototypes with it too.
"""
