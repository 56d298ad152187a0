"""The denoising job (``dss-denoise``) as a library; ``dss-filter``, the image study and the
tables use it too.
"""
