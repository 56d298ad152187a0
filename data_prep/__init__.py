"""Training data for the Pix2Pix denoiser: generated shapes -> noisy/clean clouds -> DSS render pairs.

- :mod:`data_prep.shapes`: seeded procedural families of watertight meshes (``make_shape``).
- :mod:`data_prep.sampling`: Poisson-disk sampling, Gaussian noise, PCA normals (via ``dss``).
- :mod:`data_prep.render_spec`: the shared render setting (``conf/render/pairs.yaml``).
- :mod:`data_prep.pairs`: noisy and clean renders through the same cameras and point light.
- :mod:`data_prep.shards`: deterministic, resumable, parallel ``dss-pairs/1`` shards + manifest.
- :mod:`data_prep.preview`: PNG sheets of the families and of rendered pairs.

The ``dss-prep`` app (``experiments/apps/prep.py``) drives it all from ``conf/prep.yaml``.
"""
