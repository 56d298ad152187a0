"""Pix2Pix networks of the DSS paper (appendix "Denoising Pix2Pix").

- :class:`ResNetGenerator`: 7x7 stem, 2 stride-2 downs, ``n_blocks`` residual blocks, 2 stride-2
  up-convolutions each followed by a 3x3 convolution (against checkerboard artefacts),
  reflection padding, pixel-wise normalisation, **no final tanh** (unbounded output).
- :class:`PatchDiscriminator`: the 70x70 PatchGAN C64-C128-C256-C512-C1 (for ``ndf=64``,
  ``n_layers=3``), conditional on the noisy input (it sees ``cat(noisy, image)``).
- :func:`init_xavier`: Xavier initialisation as pix2pix's ``init_type="xavier"``.

Images are (B, C, H, W) float32. The generator takes renders in their natural range (about
[0, 1], unbounded in principle) and returns images in the same range: the input normalisation
``(x - input_mean) / input_std`` and its inverse are part of the module (and so of the ONNX
export), so callers never normalise by hand.

Residual or direct prediction (``residual`` flag): with ``residual=True`` the network predicts
a correction added to the (normalised) noisy input, so it starts from the identity, which is
already the noisy baseline; it only has to learn the small difference (DnCNN, Zhang et al.
2017), which trains markedly faster on a CPU budget. The paper's model predicts the clean image
directly (``residual=False``), which is the ``paper`` preset; the CPU presets use the residual.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from .blocks import Down, Head, ResidualBlock, Stem, Up
from .norms import NormFactory, PixelNorm, build_norm, norm_spec

__all__ = ["ResNetGenerator", "PatchDiscriminator", "PlanesGenerator", "generator_from_config", "image_coords",
           "init_xavier", "covered", "apply_coverage", "SIZE_MULTIPLE"]

#: H and W of generator inputs must be multiples of this (two stride-2 downsamplings).
SIZE_MULTIPLE = 4
#: the smallest H, W the generator accepts (reflection padding at 1/4 resolution needs >= 2 px).
MIN_SIZE = 8


def init_xavier(module: nn.Module, gain: float = 0.02) -> None:
    """Xavier-normal weights (std = gain * sqrt(2 / (fan_in + fan_out))), zero biases.

    Matches pix2pix's ``init_weights(net, "xavier", init_gain=0.02)``, which the DSS paper uses
    ("default parameters of the Pix2Pix implementation" + Xavier). Affine norm layers get
    weights ~ N(1, gain) and zero bias, as there.
    """

    def _init(m: nn.Module) -> None:
        if isinstance(m, nn.Conv2d | nn.ConvTranspose2d | nn.Linear):
            nn.init.xavier_normal_(m.weight, gain=gain)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.modules.batchnorm._NormBase) and m.affine:
            nn.init.normal_(m.weight, 1.0, gain)
            nn.init.zeros_(m.bias)

    module.apply(_init)


def _channel_values(value, channels: int, name: str) -> float | list[float]:
    """A float, or a list of ``channels`` floats (one per channel) from a config value."""
    if isinstance(value, int | float):
        return float(value)
    try:
        vals = [float(v) for v in value]
    except TypeError as e:
        raise ValueError(f"{name} must be a number or a list of {channels} numbers, got {value!r}") from e
    if len(vals) != channels:
        raise ValueError(f"{name}: {len(vals)} values for {channels} channels")
    return vals


def check_image_batch(x: torch.Tensor, channels: int, multiple: int = SIZE_MULTIPLE,
                      min_size: int = MIN_SIZE, who: str = "generator") -> None:
    """Raise ValueError unless ``x`` is (B, channels, H, W) with H, W multiples of ``multiple``."""
    if x.dim() != 4:
        raise ValueError(f"{who}: expected a (B, C, H, W) tensor, got shape {tuple(x.shape)}")
    b, c, h, w = x.shape
    if c != channels:
        raise ValueError(
            f"{who}: expected {channels} channels in dim 1 of (B, C, H, W), got {c} "
            f"(shape {tuple(x.shape)}; channels-last images must be permuted first)"
        )
    if h % multiple or w % multiple or h < min_size or w < min_size:
        raise ValueError(
            f"{who}: height and width must be multiples of {multiple} and at least {min_size}, "
            f"got {h}x{w} (pad or crop the image, e.g. to "
            f"{max(min_size, h // multiple * multiple)}x{max(min_size, w // multiple * multiple)})"
        )


def _checks_enabled() -> bool:
    # Python-level shape checks would be frozen into a traced/exported graph as constants.
    return not (torch.jit.is_tracing() or torch.onnx.is_in_onnx_export())


def covered(images: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) bool: pixels of the renders (B, C, H, W) that a surface covers (any channel
    non-zero; the renders' background is exactly 0)."""
    return images.abs().amax(dim=1, keepdim=True) > 0


def apply_coverage(image: torch.Tensor, logit: torch.Tensor) -> torch.Tensor:
    """``image`` (B, C, H, W) with exact zeros where the coverage ``logit`` (B, 1, H, W) is <= 0."""
    return image * (logit > 0).to(image.dtype)


#: magnitude of the coverage logit's prior (the input's own coverage, +-1): large enough that an
#: untrained head keeps it, small enough that the head overrides it within a few hundred steps
COVERAGE_PRIOR = 2.0


class ResNetGenerator(nn.Module):
    """ResNet image-to-image generator (Johnson et al. 2016 / pix2pix, as adapted by DSS).

    Args:
        in_channels, out_channels: image channels (3 for RGB renders).
        ngf: width of the first layer; the downs double it twice (ngf, 2 ngf, 4 ngf).
        n_blocks: number of residual blocks at 1/4 resolution (paper: 9).
        norm_layer: callable ``norm_layer(num_features) -> nn.Module`` (default PixelNorm).
        residual: predict a correction added to the input (True) or the image (False, paper).
        input_mean, input_std: normalisation ``(x - mean) / std`` applied inside the module
            (and inverted on the output); 0.5/0.5 maps renders in [0, 1] to [-1, 1] as pix2pix.
            A float, or one value per channel (a list of ``in_channels``; needs
            ``in_channels == out_channels``), e.g. for the ``planes`` channel whose third
            component (about the inverse depth) has another range than the first two (the
            normal's slopes, about 0).
        init_gain: Xavier gain. pix2pix's default is 0.02 (the ``paper`` preset). Every conv
            here is followed by a normalisation, which makes it scale-invariant, so Adam's
            effective step on it is about lr / |w|: with gain 0.02 that is ~100% of the weights per
            step at lr 1e-3 and the network stalls for a long time (measured: ngf 16, 2 blocks,
            32 px, Adam 1e-3, learning to copy its input: L1 stays at 0.25 for 300 steps with
            gain 0.02, falls to 0.10 with gain 1.0). The CPU presets use 1.0 (standard Glorot).
        zero_init_head: zero the last convolution's weights so that a residual generator starts
            as the exact identity (the noisy baseline); default: ``residual``.
        coverage_head: add a second 7x7 head that predicts, per pixel, whether the *clean*
            surface covers it (a logit, :meth:`forward_with_coverage`); :meth:`forward` then
            returns the image with every pixel the head calls uncovered set to exactly 0 (the
            renders' black background). Why: SMAPE is 1 for any non-zero value over a zero
            target, so the halo that noise spreads around the silhouette costs as much as a
            wrong surface pixel unless the network can output an exact 0 there, which a
            regression head never does. The logit is ``head(features) + COVERAGE_PRIOR x (+1 where
            the input covers the pixel, -1 where it does not)``; the head starts at zero, so an
            untrained coverage head keeps the input's coverage (an identity generator stays the
            identity). The gate is a hard step: it passes no gradient to the logit, which is
            trained by its own loss (``Pix2PixModule(lambda_coverage=...)``).

    Shapes: (B, in_channels, H, W) -> (B, out_channels, H, W) for H, W multiples of 4 (>= 8);
    other sizes raise ValueError. The output is unbounded (no tanh).
    """

    size_multiple = SIZE_MULTIPLE

    def __init__(
        self,
        in_channels: int = 3,
        out_channels: int = 3,
        ngf: int = 64,
        n_blocks: int = 9,
        norm_layer: NormFactory = PixelNorm,
        residual: bool = False,
        input_mean: float | list[float] = 0.5,
        input_std: float | list[float] = 0.5,
        init_gain: float = 0.02,
        zero_init_head: bool | None = None,
        coverage_head: bool = False,
    ):
        super().__init__()
        if zero_init_head is None:
            zero_init_head = residual
        if n_blocks < 0 or ngf < 1:
            raise ValueError(f"need ngf >= 1 and n_blocks >= 0, got ngf={ngf}, n_blocks={n_blocks}")
        if residual and in_channels != out_channels:
            raise ValueError("residual=True needs in_channels == out_channels")
        mean_v, std_v = _channel_values(input_mean, in_channels, "input_mean"), _channel_values(
            input_std, in_channels, "input_std")
        if any(v <= 0 for v in (std_v if isinstance(std_v, list) else [std_v])):
            raise ValueError(f"input_std must be > 0, got {input_std}")
        if (isinstance(mean_v, list) or isinstance(std_v, list)) and in_channels != out_channels:
            raise ValueError("per-channel input_mean / input_std need in_channels == out_channels")
        self._config: dict[str, Any] = {
            "in_channels": int(in_channels),
            "out_channels": int(out_channels),
            "ngf": int(ngf),
            "n_blocks": int(n_blocks),
            "norm_layer": norm_spec(norm_layer),
            "residual": bool(residual),
            "input_mean": mean_v,
            "input_std": std_v,
            "init_gain": float(init_gain),
            "zero_init_head": bool(zero_init_head),
            "coverage_head": bool(coverage_head),
        }
        self.in_channels = in_channels
        self.residual = residual
        # floats stay Python constants (the exported graph of a scalar normalisation is unchanged);
        # per-channel values are (1, C, 1, 1) buffers outside the state dict (not weights)
        self.input_mean = self._norm_value("_input_mean", mean_v)
        self.input_std = self._norm_value("_input_std", std_v)

        self.stem = Stem(in_channels, ngf, norm_layer)
        self.down1 = Down(ngf, 2 * ngf, norm_layer)
        self.down2 = Down(2 * ngf, 4 * ngf, norm_layer)
        self.blocks = nn.Sequential(*[ResidualBlock(4 * ngf, norm_layer) for _ in range(n_blocks)])
        self.up1 = Up(4 * ngf, 2 * ngf, norm_layer)
        self.up2 = Up(2 * ngf, ngf, norm_layer)
        self.head = Head(ngf, out_channels)
        self.coverage = Head(ngf, 1) if coverage_head else None
        init_xavier(self, init_gain)
        if zero_init_head:
            # the correction starts at exactly 0 (output == input), whatever init_gain is
            nn.init.zeros_(self.head[1].weight)
        if self.coverage is not None:  # start from the input's own coverage (the prior)
            nn.init.zeros_(self.coverage[1].weight)
            nn.init.zeros_(self.coverage[1].bias)

    def _norm_value(self, name: str, value: float | list[float]):
        """``value`` itself (a float), or a (1, C, 1, 1) buffer ``name`` of a per-channel list."""
        if not isinstance(value, list):
            return value
        self.register_buffer(name, torch.tensor(value, dtype=torch.float32).reshape(1, -1, 1, 1), persistent=False)
        return None

    def _normalisation(self):
        """(mean, std): floats, or the per-channel buffers (on the module's device)."""
        mean = self._buffers["_input_mean"] if self.input_mean is None else self.input_mean
        std = self._buffers["_input_std"] if self.input_std is None else self.input_std
        return mean, std

    def config(self) -> dict[str, Any]:
        """JSON-able constructor arguments (norm layer as import path + kwargs)."""
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self._config.items()}

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> ResNetGenerator:
        """Rebuild an (untrained) generator from :meth:`config` output."""
        kwargs = dict(config)
        kwargs["norm_layer"] = build_norm(kwargs["norm_layer"])
        return cls(**kwargs)

    def forward_with_coverage(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(image (B, out_channels, H, W) before the coverage gate, coverage logit (B, 1, H, W)
        or None without a coverage head); a logit > 0 means "the clean surface covers it"."""
        if _checks_enabled():
            check_image_batch(x, self.in_channels, who=type(self).__name__)
        mean, std = self._normalisation()
        xn = (x - mean) / std
        y = self.stem(xn)
        y = self.down2(self.down1(y))
        y = self.blocks(y)
        feats = self.up2(self.up1(y))
        y = self.head(feats)
        if self.residual:
            y = y + xn
        image = y * std + mean
        if self.coverage is None:
            return image, None
        covered_in = covered(x).to(x.dtype)
        logit = self.coverage(feats) + COVERAGE_PRIOR * (2.0 * covered_in - 1.0)
        return image, logit

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        image, logit = self.forward_with_coverage(x)
        if logit is None:
            return image
        return apply_coverage(image, logit)


class PatchDiscriminator(nn.Module):
    """Conditional PatchGAN discriminator: C64-C128-C256-C512-C1 for ``ndf=64, n_layers=3``.

    Ck = 4x4 convolution with k filters, norm (not on the first layer), LeakyReLU(0.2); the
    first ``n_layers`` have stride 2, then one stride-1 layer and a stride-1 1-channel output.
    With ``n_layers=3`` each output value sees a 70x70 input patch.

    Args:
        in_channels: channels of ``cat(condition, image)`` (6 for RGB pairs).
        ndf: filters of the first layer (doubles per layer, capped at 8 ndf).
        n_layers: number of stride-2 layers (3 -> 70x70 patches).
        norm_layer: callable ``norm_layer(num_features) -> nn.Module``.
        init_gain: Xavier gain.

    Shapes: (B, in_channels, H, W) -> (B, 1, H/2^n - 2, W/2^n - 2) raw scores (LSGAN: no
    sigmoid), e.g. 256x256 -> 30x30.
    """

    def __init__(
        self,
        in_channels: int = 6,
        ndf: int = 64,
        n_layers: int = 3,
        norm_layer: NormFactory = nn.InstanceNorm2d,
        init_gain: float = 0.02,
    ):
        super().__init__()
        if n_layers < 1 or ndf < 1:
            raise ValueError(f"need ndf >= 1 and n_layers >= 1, got ndf={ndf}, n_layers={n_layers}")
        self._config: dict[str, Any] = {
            "in_channels": int(in_channels),
            "ndf": int(ndf),
            "n_layers": int(n_layers),
            "norm_layer": norm_spec(norm_layer),
            "init_gain": float(init_gain),
        }
        self.in_channels = in_channels
        self.n_layers = n_layers
        layers: list[nn.Module] = [
            nn.Conv2d(in_channels, ndf, kernel_size=4, stride=2, padding=1),
            nn.LeakyReLU(0.2, inplace=True),
        ]
        ch = ndf
        for i in range(1, n_layers + 1):
            out = ndf * min(2**i, 8)
            stride = 2 if i < n_layers else 1
            layers += [
                nn.Conv2d(ch, out, kernel_size=4, stride=stride, padding=1),
                norm_layer(out),
                nn.LeakyReLU(0.2, inplace=True),
            ]
            ch = out
        layers.append(nn.Conv2d(ch, 1, kernel_size=4, stride=1, padding=1))
        self.model = nn.Sequential(*layers)
        init_xavier(self, init_gain)

    @property
    def receptive_field(self) -> int:
        """Side of the input patch each output value sees (70 for n_layers=3)."""
        rf = 1
        for k, s in reversed([(4, 2)] * self.n_layers + [(4, 1), (4, 1)]):
            rf = (rf - 1) * s + k
        return rf

    @property
    def min_input_size(self) -> int:
        """Smallest H, W giving a >= 2x2 map before the last layer (instance norm needs > 1 px)."""
        return 2**self.n_layers * 3

    def config(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self._config.items()}

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> PatchDiscriminator:
        kwargs = dict(config)
        kwargs["norm_layer"] = build_norm(kwargs["norm_layer"])
        return cls(**kwargs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if _checks_enabled():
            check_image_batch(x, self.in_channels, multiple=1, min_size=self.min_input_size,
                              who=type(self).__name__)
        return self.model(x)


# ------------------------------------------------------------------------------ planes channel
def image_coords(x: torch.Tensor, fov_deg: float) -> torch.Tensor:
    """Normalised image coordinates (1, 2, H, W) of the pixel centres of full renders ``x``
    (B, C, H, W): ``(u - W/2) / f`` and ``(v - H/2) / f`` with ``u = column + 0.5``,
    ``f = 0.5 W / tan(fov / 2)`` (the cameras of ``dss.cameras.look_at`` with the render spec's
    horizontal field of view). Tensor operations on ``x``'s shape only, so H and W stay dynamic
    axes of an ONNX export."""
    import math

    t = math.tan(math.radians(float(fov_deg)) / 2)
    ones_w = torch.ones_like(x[:1, :1, :1, :])  # (1, 1, 1, W)
    ones_h = torch.ones_like(x[:1, :1, :, :1])  # (1, 1, H, 1)
    w = ones_w.sum(3, keepdim=True)
    h = ones_h.sum(2, keepdim=True)
    u = ones_w.cumsum(3) - 0.5
    v = ones_h.cumsum(2) - 0.5
    xs = (2.0 * u / w - 1.0) * t  # (u - W/2) / (0.5 W / t)
    ys = (v - 0.5 * h) * (2.0 * t / w)
    return torch.cat([xs * ones_h, ys * ones_w], dim=1)


class PlanesGenerator(nn.Module):
    """The Pix2Pix ResNet generator for renders in the ``planes`` channel, working on per-pixel
    inverse depth and normal instead of the raw plane coefficients.

    A planes pixel holds ``a`` with ``1/z = a . (x, y, 1)`` at its normalised image coordinates
    ``(x, y)``; the inverse depth at the pixel is therefore entangled with the pixel's position
    (``a_0 x`` reaches the size of ``1/z`` itself at a tilted surface near the image border), which
    a convolutional network, blind to absolute position, cannot undo: averaging the planes of
    neighbouring pixels extrapolates their noisy normals instead of fitting their depths. This
    generator reads, per pixel, ``inv = a . (x, y, 1)`` and the unit normal facing the camera
    ``m = -a / |a|`` (0 on the background), corrects both and writes the plane through the
    corrected point with the corrected normal back: ``a' = m' inv' / (m' . (x, y, 1))``
    (``|m' . (x, y, 1)|`` kept at least ``min_cos |(x, y, 1)|``, as
    :func:`dss.shading.plane_coefficients` does). Pixels the input leaves as background stay 0.

    The correction is residual, but on a smoothed base: the 4 features blurred by a Gaussian of
    ``base_blur_px`` pixels over the covered pixels (normalised convolution; 0: the features
    themselves). A ResNet generator's output path comes from its quarter-resolution bottleneck,
    so it cannot reproduce (and subtract) the per-pixel noise of a residual base; measured on
    the validation renders at 1% noise, a 4 px blur alone takes the implied depth's median error
    from 0.0094 to 0.0067 and the normals' from 31 to 21 degrees. The network sees the raw and the
    blurred features (8 channels: ResNetGenerator's stem, downs, blocks and ups) and, with
    ``skip``, its full-resolution stem features again before the head (what the blur removed at
    occlusion edges can come back). The head starts at zero: the untrained generator outputs the
    blurred base (exactly the input with ``base_blur_px=0``, except planes within ``min_cos`` of
    edge-on, clamped like the renderer's own).

    ``(x, y)`` come from ``coords`` (B, 2, H, W) when given (training crops, whose pixels are not
    centred), else from the image size and ``fov_deg`` (full renders: the pipeline and the ONNX
    export). ``input_mean``/``input_std``: per feature (inv, m_x, m_y, m_z), for both the raw and
    the blurred copy.

    ``uncertainty``: the head has a fifth channel, the log of the predicted Laplace scale ``b`` of
    the output's inverse-depth error per pixel (1 / bbox diagonals; trained by a negative
    log-likelihood in :class:`pix2pix.module.Pix2PixModule`, read by the plane fusion's
    ``uncertainty`` option). It starts at ``log(uncertainty_init)`` (the head is zero-initialised).
    :meth:`forward` still returns the planes alone; :meth:`forward_with_uncertainty` returns
    both, and the ONNX export adds it as a second output ``log_scale`` (B, 1, H, W).

    Shapes: (B, 3, H, W) planes -> (B, 3, H, W) planes.
    """

    size_multiple = SIZE_MULTIPLE
    in_channels = 3

    def __init__(self, ngf: int = 16, n_blocks: int = 6, norm_layer: NormFactory = PixelNorm,
                 input_mean: float | list[float] = (0.4, 0.0, 0.0, -0.25),
                 input_std: float | list[float] = (0.5, 0.4, 0.4, 0.4), init_gain: float = 1.0,
                 fov_deg: float = 40.0, min_cos: float = 0.05, base_blur_px: float = 3.0, skip: bool = True,
                 uncertainty: bool = False, uncertainty_init: float = 0.01, **_ignored: Any):
        super().__init__()
        if not 1.0 <= float(fov_deg) <= 170.0:
            raise ValueError(f"fov_deg must be in [1, 170], got {fov_deg}")
        if float(base_blur_px) < 0:
            raise ValueError(f"base_blur_px must be >= 0, got {base_blur_px}")
        if n_blocks < 0 or ngf < 1:
            raise ValueError(f"need ngf >= 1 and n_blocks >= 0, got ngf={ngf}, n_blocks={n_blocks}")
        mean = _channel_values(input_mean if isinstance(input_mean, int | float) else list(input_mean), 4, "input_mean")
        std = _channel_values(input_std if isinstance(input_std, int | float) else list(input_std), 4, "input_std")
        mean = [mean] * 4 if isinstance(mean, float) else mean
        std = [std] * 4 if isinstance(std, float) else std
        if any(v <= 0 for v in std):
            raise ValueError(f"input_std must be > 0, got {input_std}")
        self.fov_deg, self.min_cos = float(fov_deg), float(min_cos)
        self.base_blur_px, self.skip = float(base_blur_px), bool(skip)
        self.register_buffer("_mean", torch.tensor(mean).view(1, 4, 1, 1), persistent=False)
        self.register_buffer("_std", torch.tensor(std).view(1, 4, 1, 1), persistent=False)
        r = max(1, int(math.ceil(3 * self.base_blur_px))) if self.base_blur_px > 0 else 0
        k = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float32) ** 2 / (2 * max(self.base_blur_px, 1e-6) ** 2))
        k = (k / k.sum()).view(1, 1, 1, -1).repeat(5, 1, 1, 1)  # the 4 features and the coverage
        self.register_buffer("_blur_w", k.contiguous(), persistent=False)
        self.register_buffer("_blur_h", k.transpose(2, 3).contiguous(), persistent=False)
        self.stem = Stem(8, ngf, norm_layer)
        self.down1 = Down(ngf, 2 * ngf, norm_layer)
        self.down2 = Down(2 * ngf, 4 * ngf, norm_layer)
        self.blocks = nn.Sequential(*[ResidualBlock(4 * ngf, norm_layer) for _ in range(n_blocks)])
        self.up1 = Up(4 * ngf, 2 * ngf, norm_layer)
        self.up2 = Up(2 * ngf, ngf, norm_layer)
        if not float(uncertainty_init) > 0:
            raise ValueError(f"uncertainty_init must be > 0, got {uncertainty_init}")
        self.predicts_uncertainty = bool(uncertainty)
        self.uncertainty_init = float(uncertainty_init)
        self.head = Head(2 * ngf if self.skip else ngf, 5 if self.predicts_uncertainty else 4)
        init_xavier(self, init_gain)
        nn.init.zeros_(self.head[1].weight)
        self._config = {"kind": "planes", "ngf": int(ngf), "n_blocks": int(n_blocks), "norm_layer": norm_spec(norm_layer),
                        "input_mean": mean, "input_std": std, "init_gain": float(init_gain), "fov_deg": self.fov_deg,
                        "min_cos": self.min_cos, "base_blur_px": self.base_blur_px, "skip": self.skip,
                        "in_channels": 3, "out_channels": 3, "residual": True, "coverage_head": False}
        if self.predicts_uncertainty:  # only then: the configs of earlier models stay as they were
            self._config.update(uncertainty=True, uncertainty_init=self.uncertainty_init)

    def config(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self._config.items()}

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> PlanesGenerator:
        kwargs = {k: v for k, v in config.items() if k not in ("kind", "in_channels", "out_channels", "residual",
                                                              "coverage_head")}
        kwargs["norm_layer"] = build_norm(kwargs["norm_layer"])
        return cls(**kwargs)

    def features(self, a: torch.Tensor, coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(inv (B, 1, H, W), m (B, 3, H, W)) of planes ``a`` (B, 3, H, W) at ``coords``."""
        inv = a[:, 0:1] * coords[:, 0:1] + a[:, 1:2] * coords[:, 1:2] + a[:, 2:3]
        m = -a / a.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return inv, m

    def planes(self, inv: torch.Tensor, m: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """Planes (B, 3, H, W) through the points at inverse depth ``inv`` on the pixels' rays
        with normals ``m`` (unit, facing the camera)."""
        ray = torch.cat([coords, torch.ones_like(coords[:, :1])], dim=1)
        d = (m * ray).sum(1, keepdim=True)
        lim = self.min_cos * ray.norm(dim=1, keepdim=True)
        d = torch.where(d < 0, torch.minimum(d, -lim), torch.maximum(d, lim))
        return m * inv / d

    def _blurred(self, f: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """Normalised Gaussian blur of features ``f`` (B, C, H, W) over the covered pixels."""
        if self.base_blur_px <= 0:
            return f
        r = (self._blur_w.shape[-1] - 1) // 2
        x = torch.cat([f * cov, cov], dim=1)
        x = nn.functional.conv2d(x, self._blur_w, padding=(0, r), groups=5)
        x = nn.functional.conv2d(x, self._blur_h, padding=(r, 0), groups=5)
        w = x[:, -1:]
        return torch.where(w > 1e-3, x[:, :-1] / w.clamp_min(1e-3), f)

    def forward_with_coverage(self, x: torch.Tensor, coords: torch.Tensor | None = None):
        a, _ = self.forward_with_uncertainty(x, coords)
        return a, None

    def forward_with_uncertainty(self, x: torch.Tensor, coords: torch.Tensor | None = None):
        """(planes (B, 3, H, W), log Laplace scale of the inverse depth (B, 1, H, W) or None)."""
        if _checks_enabled():
            check_image_batch(x, 3, who=type(self).__name__)
        if coords is None:
            coords = image_coords(x, self.fov_deg)
        cov = (x.abs().amax(dim=1, keepdim=True) > 0).to(x.dtype)
        inv, m = self.features(x, coords)
        raw = torch.cat([inv, m], dim=1) * cov
        base = self._blurred(raw, cov)
        raw_n = (raw - self._mean) / self._std
        base_n = (base - self._mean) / self._std
        y0 = self.stem(torch.cat([raw_n, base_n], dim=1))
        y = self.up2(self.up1(self.blocks(self.down2(self.down1(y0)))))
        if self.skip:
            y = torch.cat([y, y0], dim=1)
        h = self.head(y)
        out = (base_n + h[:, :4]) * self._std + self._mean
        m2 = torch.nn.functional.normalize(out[:, 1:], dim=1, eps=1e-6)
        a = self.planes(out[:, :1], m2, coords.expand(x.shape[0], -1, -1, -1)) * cov
        log_b = h[:, 4:5] + math.log(self.uncertainty_init) if self.predicts_uncertainty else None
        return a, log_b

    def forward(self, x: torch.Tensor, coords: torch.Tensor | None = None) -> torch.Tensor:
        return self.forward_with_coverage(x, coords)[0]


def generator_from_config(config: dict[str, Any]) -> nn.Module:
    """The generator a :meth:`config` describes (:class:`PlanesGenerator` for ``kind: planes``)."""
    if config.get("kind") == "planes":
        return PlanesGenerator.from_config(config)
    return ResNetGenerator.from_config(config)
