"""Differentiable Surface Splatting."""
