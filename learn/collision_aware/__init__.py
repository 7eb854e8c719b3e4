"""Collision-aware generative learner (seed 002): a canonical, unposed and deshaped garment space.

``diffusion`` (body surface values extended into space by Gaussian-sample averaging), ``fields``
(the diffused skinning weights and shape blendshapes distilled into small MLPs), ``sdf`` (a
signed-distance MLP of the canonical body), ``garment_model`` (posing a canonical garment with the
diffused fields, and its inverse), ``canonicalize`` (projection of simulated frames into the
canonical space by optimization, cached per shard), ``vae`` (the garment VAE and its
self-supervised collision loss), ``regressor`` ((pose, shape, style) -> latent, per frame),
``motion_descriptor`` and ``recurrent_regressor`` (the GRU over a motion sequence's descriptor,
shape and style -> latent per frame, for motion datasets), ``model`` (the
assembled predictor), ``train`` (the stages behind ``drape train collision_aware``).
"""
