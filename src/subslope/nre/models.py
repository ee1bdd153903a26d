"""Likelihood-ratio estimator ``f(γ, x) = ln r̂(x | γ)`` for 1-channel lens images.

Structure (docs/estimator.md)::

    x (B, 1, H, W) ──trunk──► z (B, C)            evaluated once per image
    (z, γ) ──normalise γ, concat──► MLP ──► logit  evaluated for every (image, γ) pair

The logit is the log likelihood-to-evidence ratio ``ln r̂(x|γ) = ln p(x|γ) − ln p(x)``
of a classifier trained with :mod:`subslope.nre.loss` (Hermans, Begy & Louppe 2020);
``sigmoid(logit)`` is the classifier output ŝ.

The trunk is a ResNet (He et al. 2016) adapted to 1-channel images of ~100×100 pixels:

- ``depth`` 10/18/34 use basic blocks, 50/101 bottleneck blocks (ResNet-50 is the
  paper's choice); ``width`` multiplies the channel counts (64·width at the first stage).
- ``stem``: ``"imagenet"`` (7×7 stride-2 conv + 3×3 stride-2 max-pool: 100 → 25 pixels
  before the first stage, as torchvision), ``"compact"`` (3×3 stride-2 conv, no pool:
  100 → 50, keeps more small-scale structure at 4× the cost of the first stage), or
  ``"full"`` (3×3 stride-1 conv: full resolution, most expensive).
- Global average pooling gives the latent vector ``z`` (``C = 64·width·2³·expansion``).

γ is normalised with the training-label mean and std, kept in the model as buffers so a
checkpoint carries them, then concatenated to ``z`` and passed through ``head`` hidden
layers (SiLU) to one logit.

Any module mapping ``(B, ...) → (B, C)`` can be used as trunk (:class:`RatioEstimator`),
which is how the toy tests use the same head/loss code on small vectors.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import nn

__all__ = [
    "BasicBlock",
    "Bottleneck",
    "ResNetTrunk",
    "RatioEstimator",
    "DEFAULT_ARCH",
    "PRESETS",
    "build_model",
    "model_card",
    "count_parameters",
]

_LAYOUTS = {
    10: ("basic", (1, 1, 1, 1)),
    18: ("basic", (2, 2, 2, 2)),
    34: ("basic", (3, 4, 6, 3)),
    50: ("bottleneck", (3, 4, 6, 3)),
    101: ("bottleneck", (3, 4, 23, 3)),
}
_STEMS = ("imagenet", "compact", "full")

#: Every architecture key with its default (``build_model`` fills missing keys from here).
DEFAULT_ARCH: dict[str, Any] = {
    "depth": 18,
    "width": 0.125,
    "stem": "imagenet",
    "head": [128, 128],
    "in_channels": 1,
}

#: Named architectures: ``build_model({"preset": "reduced"})`` or ``build_model(PRESETS[...])``.
PRESETS: dict[str, dict[str, Any]] = {
    # ~2.0e5 parameters; trains on 2 CPU cores (see docs/estimator.md for throughput).
    "reduced": {"depth": 18, "width": 0.125, "stem": "imagenet", "head": [128, 128]},
    # The paper's network: ResNet-50, full width (~2.4e7 parameters).
    "resnet50": {"depth": 50, "width": 1.0, "stem": "imagenet", "head": [256, 256]},
}


def _conv3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


def _conv1(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, stride=stride, bias=False)


def _shortcut(cin: int, cout: int, stride: int) -> nn.Module:
    """Identity, or a strided 1×1 projection when the shape changes (ResNet v1)."""
    if stride == 1 and cin == cout:
        return nn.Identity()
    return nn.Sequential(_conv1(cin, cout, stride), nn.BatchNorm2d(cout))


class BasicBlock(nn.Module):
    """Two 3×3 convolutions with an identity (or 1×1 projection) shortcut."""

    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int = 1):
        super().__init__()
        cout = planes * self.expansion
        self.conv1, self.bn1 = _conv3(cin, planes, stride), nn.BatchNorm2d(planes)
        self.conv2, self.bn2 = _conv3(planes, cout), nn.BatchNorm2d(cout)
        self.act = nn.ReLU(inplace=True)
        self.shortcut = _shortcut(cin, cout, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.act(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.act(out + self.shortcut(x))


class Bottleneck(nn.Module):
    """1×1 reduce, 3×3 (strided, as torchvision's ResNet v1.5), 1×1 expand ×4."""

    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int = 1):
        super().__init__()
        cout = planes * self.expansion
        self.conv1, self.bn1 = _conv1(cin, planes), nn.BatchNorm2d(planes)
        self.conv2, self.bn2 = _conv3(planes, planes, stride), nn.BatchNorm2d(planes)
        self.conv3, self.bn3 = _conv1(planes, cout), nn.BatchNorm2d(cout)
        self.act = nn.ReLU(inplace=True)
        self.shortcut = _shortcut(cin, cout, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.act(self.bn1(self.conv1(x)))
        out = self.act(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.act(out + self.shortcut(x))


class ResNetTrunk(nn.Module):
    """ResNet feature extractor ``(B, C_in, H, W) → (B, out_features)``."""

    def __init__(
        self, depth: int = 18, width: float = 1.0, stem: str = "imagenet", in_channels: int = 1
    ):
        super().__init__()
        if depth not in _LAYOUTS:
            raise ValueError(f"arch.depth must be one of {sorted(_LAYOUTS)}, got {depth!r}")
        if stem not in _STEMS:
            raise ValueError(f"arch.stem must be one of {list(_STEMS)}, got {stem!r}")
        if not (isinstance(width, (int, float)) and width > 0):
            raise ValueError(f"arch.width must be a positive number, got {width!r}")
        kind, counts = _LAYOUTS[depth]
        block = BasicBlock if kind == "basic" else Bottleneck
        c0 = max(4, int(round(64 * width)))
        if stem == "imagenet":
            self.stem = nn.Sequential(
                nn.Conv2d(in_channels, c0, 7, stride=2, padding=3, bias=False),
                nn.BatchNorm2d(c0),
                nn.ReLU(inplace=True),
                nn.MaxPool2d(3, stride=2, padding=1),
            )
        else:
            stride = 2 if stem == "compact" else 1
            self.stem = nn.Sequential(
                _conv3(in_channels, c0, stride), nn.BatchNorm2d(c0), nn.ReLU(inplace=True)
            )
        stages, cin = [], c0
        for i, n in enumerate(counts):
            planes = c0 * 2**i
            blocks = []
            for j in range(n):
                blocks.append(block(cin, planes, stride=2 if (i > 0 and j == 0) else 1))
                cin = planes * block.expansion
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.Sequential(*stages)
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.out_features = cin
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        # Zero-init the last BN of each residual branch: every block starts as identity,
        # which stabilises early training of deep trunks (Goyal et al. 2017).
        for m in self.modules():
            if isinstance(m, BasicBlock):
                nn.init.zeros_(m.bn2.weight)
            elif isinstance(m, Bottleneck):
                nn.init.zeros_(m.bn3.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pool(self.stages(self.stem(x))).flatten(1)


class RatioEstimator(nn.Module):
    """``ln r̂(x|γ)`` from a trunk ``x → z`` and a head ``(z, γ) → logit``.

    Parameters
    ----------
    trunk:
        Module mapping a batch ``(B, ...)`` to ``(B, latent_dim)``.
    latent_dim:
        Size of the trunk output.
    head:
        Hidden layer sizes of the dense head (SiLU activations).
    gamma_mean, gamma_std:
        Normalisation of γ (training-label mean and std), stored as buffers.
    image_ndim:
        Axes of one sample as the trunk sees it; 3 means 1-channel images ``(1, H, W)``,
        given as ``(H, W)`` (one image), ``(B, H, W)`` or ``(B, 1, H, W)`` (batches).
    """

    def __init__(
        self,
        trunk: nn.Module,
        latent_dim: int,
        head: Sequence[int] = (128, 128),
        *,
        gamma_mean: float = 0.0,
        gamma_std: float = 1.0,
        image_ndim: int = 3,
    ):
        super().__init__()
        if not gamma_std > 0:
            raise ValueError(f"gamma_std must be > 0, got {gamma_std!r}")
        self.trunk = trunk
        self.image_ndim = image_ndim
        layers, cin = [], latent_dim + 1
        for h in head:
            layers += [nn.Linear(cin, int(h)), nn.SiLU()]
            cin = int(h)
        layers.append(nn.Linear(cin, 1))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("gamma_mean", torch.tensor(float(gamma_mean)))
        self.register_buffer("gamma_std", torch.tensor(float(gamma_std)))
        self.arch: dict[str, Any] | None = None  # set by build_model

    # -- pieces -----------------------------------------------------------------------
    def _batch(self, x: torch.Tensor) -> tuple[torch.Tensor, bool]:
        """Batched input for the trunk and whether ``x`` was a single sample.

        With ``image_ndim = 3`` (1-channel images): ``(H, W)`` is one image, ``(B, H, W)``
        and ``(B, 1, H, W)`` are batches. Otherwise ``image_ndim`` axes are one sample and
        ``image_ndim + 1`` axes a batch.
        """
        k = self.image_ndim
        if k == 3:
            if x.ndim == 2:
                return x[None, None], True
            if x.ndim == 3:
                return x[:, None], False
            if x.ndim == 4:
                return x, False
            raise ValueError(
                f"x must have shape (H, W), (B, H, W) or (B, 1, H, W), got {tuple(x.shape)}"
            )
        if x.ndim == k:
            return x[None], True
        if x.ndim == k + 1:
            return x, False
        raise ValueError(
            f"x must have {k} (one sample) or {k + 1} (batch) axes, got shape {tuple(x.shape)}"
        )

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """Trunk features ``z`` of a batch ``(B, ...)`` → ``(B, C)``."""
        return self.trunk(x)

    def head(self, z: torch.Tensor, gamma: torch.Tensor) -> torch.Tensor:
        """Logits for features ``z (..., C)`` and ``gamma (...)`` (broadcast together)."""
        g = (
            torch.as_tensor(gamma, dtype=z.dtype, device=z.device) - self.gamma_mean.to(z.dtype)
        ) / self.gamma_std.to(z.dtype)
        shape = torch.broadcast_shapes(z.shape[:-1], g.shape)
        z = z.expand(*shape, z.shape[-1])
        g = g.expand(shape).unsqueeze(-1)
        return self.mlp(torch.cat((z, g), dim=-1)).squeeze(-1)

    # -- public -----------------------------------------------------------------------
    def forward(self, gamma: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``ln r̂(x|γ)``; the trunk runs once on ``x`` whatever the shape of ``gamma``.

        ``x``: one image ``(H, W)`` or a batch ``(B, H, W)``/``(B, 1, H, W)``.
        ``gamma``: broadcast against the batch axis, e.g. ``()``, ``(B,)`` or ``(K, B)``
        (``K`` sets of γ per image, as the loss uses for positives and negatives).
        Returns the broadcast shape of ``gamma`` and ``(B,)`` (``()`` for one image and
        scalar γ).
        """
        xb, single = self._batch(x)
        z = self.embed(xb)
        gamma = torch.as_tensor(gamma, dtype=z.dtype, device=z.device)
        if single:
            return self.head(z[0], gamma)
        return self.head(z, gamma)

    def log_ratio_grid(
        self, x: torch.Tensor, gammas: torch.Tensor, *, chunk: int | None = None
    ) -> torch.Tensor:
        """``ln r̂(x_b|γ_g)`` for every image and every grid value: ``(B, G)`` (``(G,)`` unbatched).

        The trunk is evaluated once per image (in chunks of ``chunk`` images when given),
        the head on all ``B × G`` pairs.
        """
        xb, single = self._batch(x)
        gammas = torch.as_tensor(gammas)
        if gammas.ndim != 1:
            raise ValueError(f"gammas must be a 1-D grid, got shape {tuple(gammas.shape)}")
        chunks = [xb] if chunk is None else list(torch.split(xb, chunk))
        out = []
        for xc in chunks:
            z = self.embed(xc)
            g = gammas.to(dtype=z.dtype, device=z.device)
            out.append(self.head(z[:, None, :], g[None, :]))
        res = torch.cat(out, dim=0)
        return res[0] if single else res


def _resolve_arch(arch: Mapping[str, Any] | None) -> dict[str, Any]:
    arch = dict(arch or {})
    preset = arch.pop("preset", None)
    base = copy.deepcopy(DEFAULT_ARCH)
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"arch.preset must be one of {sorted(PRESETS)}, got {preset!r}")
        base.update(copy.deepcopy(PRESETS[preset]))
    unknown = set(arch) - set(DEFAULT_ARCH)
    if unknown:
        raise ValueError(
            f"arch: unknown key(s) {sorted(unknown)}; allowed: {sorted(DEFAULT_ARCH) + ['preset']}"
        )
    base.update(arch)
    base["head"] = [int(h) for h in base["head"]]
    return base


def build_model(
    arch: Mapping[str, Any] | None = None, *, gamma_mean: float = 0.0, gamma_std: float = 1.0
) -> RatioEstimator:
    """ResNet ratio estimator from a plain config dict.

    Keys (defaults in :data:`DEFAULT_ARCH`): ``depth`` (10, 18, 34, 50, 101), ``width``
    (channel multiplier), ``stem`` (``imagenet``/``compact``/``full``), ``head`` (hidden
    sizes), ``in_channels``; or ``preset`` (:data:`PRESETS`) with overrides.
    """
    a = _resolve_arch(arch)
    trunk = ResNetTrunk(a["depth"], a["width"], a["stem"], a["in_channels"])
    model = RatioEstimator(
        trunk, trunk.out_features, a["head"], gamma_mean=gamma_mean, gamma_std=gamma_std
    )
    model.arch = a
    return model


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def model_card(model: RatioEstimator) -> dict[str, Any]:
    """``{"arch": ..., "n_params": ...}``: enough to rebuild ``model`` with :func:`build_model`."""
    if model.arch is None:
        raise ValueError("model_card: the model was not built by build_model (no arch recorded)")
    return {
        "arch": copy.deepcopy(model.arch),
        "n_params": count_parameters(model),
        "gamma_mean": float(model.gamma_mean),
        "gamma_std": float(model.gamma_std),
    }
