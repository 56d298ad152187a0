"""The shape-from-rendering job (``dss-deform``) as a library: its inputs (the target, the start
shape, the 2D experiments' camera), the budget presets, the coarse-to-fine stages and the
outputs. The app is ``experiments/apps/deform.py``; the deformation studies use these too."""
