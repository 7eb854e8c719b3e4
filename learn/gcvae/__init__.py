"""GCVAE (seed 004, CLOTH3D): garments as per-vertex offsets and a mask on a common body mesh,
a variational auto-encoder of Chebyshev graph convolutions with segment-aware pooling.

Modules: ``hyperparameters`` (every size and weight), ``body_mesh`` (the common mesh, its
segments and dual topology), ``registration`` (garment -> offsets + mask and back),
``static_set`` (rest-pose garments on sampled bodies, registered), ``dynamic_set`` (frames of
motion datasets, registered per sequence, for the dynamic variant), ``chebyshev`` (the graph
convolution), ``pooling`` (the segment-aware hierarchy), ``model`` (the VAE, static or dynamic by its condition),
``losses``, ``train``, ``evaluate``, ``sample`` (garments from the latent space), ``plots``,
``synthetic`` (tiny static sets and motion datasets for tests).
"""
