"""The denoising job (``dss-denoise``) as a library; ``dss-filter``, the image study and the
tables use it too. Nothing here imports an app.

- :mod:`~experiments.denoising.job`: the job's stages in the order ``dss-denoise`` runs them;
- :mod:`~experiments.denoising.settings`: the settings resolved for one cloud into one frozen
  :class:`~experiments.denoising.settings.Settings` (noise-level tables, neighbourhood, budget,
  render channel, plane fusion), the config never changed;
- :mod:`~experiments.denoising.inputs`: the input cloud, its outliers and noise level, the ground
  truth, the output path;
- :mod:`~experiments.denoising.reference_generators`: the generators of ``conf/reference``;
  :mod:`~experiments.denoising.references` makes one from the config;
- :mod:`~experiments.denoising.refine`: DSS's cycles, the outlier projection and the plane fusion
  in the input's units, the written normals;
- :mod:`~experiments.denoising.scoring` and :mod:`~experiments.denoising.figures`: metrics and
  figures.
"""
