"""Pix2Pix image denoiser of DSS (paper appendix "Denoising Pix2Pix").

Images are (B, C, H, W) float32 tensors here (``dss`` uses (V, H, W, C)).

- :mod:`pix2pix.networks`: ResNet generator (no tanh) and 70x70 PatchGAN; :mod:`pix2pix.blocks`,
  :mod:`pix2pix.norms` (PixelNorm).
- :mod:`pix2pix.module`: the LightningModule (manual G/D optimisation, LSGAN + L1).
- :mod:`pix2pix.datamodule`, :mod:`pix2pix.shards`, :mod:`pix2pix.augment`: streaming the
  ``dss-pairs/1`` shards, lighting-safe augmentation.
- :mod:`pix2pix.export` (ONNX + metadata) and :mod:`pix2pix.runtime` (onnxruntime, torch-free).
- :mod:`pix2pix.metrics`: L1 / SMAPE / PSNR; :mod:`pix2pix.testing`: synthetic datasets.

Submodules are imported on demand (``import pix2pix.runtime`` does not import torch).
"""
