"""UV-image learner (seed 001, pixel-based framework), in torch.

``pixels`` (cloth pixels <-> front/back UV images), ``frames`` (body-embedded points and
tangent frames), ``features`` (joint rotations, shape/style conditioning), ``decoder``
(whole-image transposed-conv decoder), ``pca`` (fully connected 128-PC variant),
``losses`` (masked pixel and normal losses), ``model`` (:class:`UVImageLearner`),
``targets`` (training targets from shards), ``garment`` (the dataset's template),
``train`` (registry fit/load).
"""
