"""The on-drone trajectory predictor: a shallow transformer with altitude AdaIN (SPEC §4).

Reading order: :class:`PredictorConfig` (what can be changed), the building blocks
(:class:`AltitudeAdaIN`, :class:`Attention`, the encoder and decoder layers) and the model
:class:`TrajectoryTransformer`, whose ``forward`` reads top to bottom::

    features (B, L_p, F) [box size x z / 50 m] --input projection--> (B, L_p, d) + positions
      -> [encoder layer -> + AdaIN(altitude)] x n_encoder_layers      memory (B, L_p, d)
    L_f learned queries (L_f, d) + sinusoidal positions L_p .. L_p + L_f - 1
      -> [decoder layer (self-attention, cross-attention to memory)] x n_decoder_layers
      -> [AdaIN(altitude) over channels] -> linear head (x, y) x frame scale   (B, L_f, 2) m

The same weights serve every target: targets are just more rows of the batch.

Where AdaIN sits, and why. A drone at altitude h sees the ground through a footprint of
``2 h tan(hfov / 2)`` m: the same box offset in the image is a ground offset proportional to h.
A model that reads boxes and outputs metres must therefore multiply by h, and a drone that
always flies at one altitude cannot learn that from its own data: each drone bakes its own
altitude's scale into all its weights, and FedAvg averages incompatible models (measured: the
federated model ended 100x worse than the same model on pooled data). Two AdaIN sites:

* ``head``: on the decoder output, just before the linear head, normalised over the channels
  of each step (so it also exists with L_f = 1), with the style starting at ``mu = 0``,
  ``sigma = h / 50 m``: the head's output, and so the predicted offset, is proportional to
  the altitude from the start; A and b then learn what deviates from that. Every drone then
  learns the same altitude-free map from image to normalised offset.
* ``encoder``: Eq. 6 as SPEC §4 states it, statistics over time, as a residual branch after
  each encoder layer (``x <- x + AdaIN_h(x)``: normalising the residual stream itself would
  erase each window's mean, which says where the target is), starting as plain
  normalisation. It alone does not help (the paper setting keeps only it); with the head site
  it does a little (docs/fl.md).

Box sizes. A vehicle of ground size s m seen from altitude h fills ``s / footprint(h)`` of the
image: box width and height scale as 1 / h, so the same vehicle is 3x smaller at 60 m than
at 20 m and every drone feeds the encoder inputs of its own scale. With ``box_size =
"metric"`` the model multiplies the box width and height features by the step's altitude
feature z / 50 m, which makes them proportional to the vehicle's ground size, the same on
every drone; ``"image"`` (the paper's) reads them as the image gives them.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields, replace
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from dronefl.models.windows import (
    ALTITUDE_FEATURE,
    ALTITUDE_SCALE_M,
    BOX_DIM,
    BOX_SIZE_FEATURES,
    FEATURE_DIM,
    PAPER_FIELD_M,
    PositionFrame,
)
from dronefl.settings import ADAIN_SITES, BOX_SIZES, STYLE_INITS

Variant = Literal["dronefl", "plain", "large"]
VARIANTS: tuple[str, ...] = ("dronefl", "plain", "large")
_METRIC_FEATURES = {"metric": BOX_SIZE_FEATURES, "ground": slice(0, BOX_DIM)}


@dataclass(frozen=True)
class PredictorConfig:
    """Architecture of the trajectory transformer.

    ``past_steps`` L_p and ``future_steps`` L_f are in samples (0.2 s each at 5 Hz).
    ``adain`` turns on the altitude AdaIN layers at ``adain_sites`` (see :data:`ADAIN_SITES`),
    the ``head`` one starting from ``head_style_init`` (see :data:`STYLE_INITS`); ``box_size``
    how box width and height are read (see :data:`BOX_SIZES`; ``metric`` needs the altitude
    feature, so ``input_dim`` >= FEATURE_DIM); ``relative``
    means the model's inputs and outputs are horizontal positions relative to the drone at time
    t (position invariance), else absolute positions around the centre of a ``field_m`` =
    (width, height) m field; with ``field_m`` it sets the output scale and how windows must be
    built (:attr:`frame`).
    """

    past_steps: int = 10
    future_steps: int = 5
    input_dim: int = FEATURE_DIM
    d_model: int = 16
    n_heads: int = 4
    n_encoder_layers: int = 2
    n_decoder_layers: int = 2
    d_ff: int = 32
    dropout: float = 0.1
    adain: bool = True
    adain_sites: tuple[str, ...] = ("encoder", "head")
    head_style_init: str = "altitude"
    box_size: str = "image"
    relative: bool = True
    field_m: tuple[float, float] = PAPER_FIELD_M

    @property
    def frame(self) -> PositionFrame:
        """The frame of the model's horizontal positions (inputs and outputs)."""
        return PositionFrame(self.relative, self.field_m)

    def __post_init__(self) -> None:
        if not set(self.adain_sites) <= set(ADAIN_SITES) or not self.adain_sites:
            raise ValueError(
                f"PredictorConfig.adain_sites must be a non-empty subset of {ADAIN_SITES}, "
                f"got {self.adain_sites}"
            )
        if self.head_style_init not in STYLE_INITS:
            raise ValueError(
                f"PredictorConfig.head_style_init must be one of {STYLE_INITS}, "
                f"got {self.head_style_init!r}"
            )
        if self.box_size not in BOX_SIZES:
            raise ValueError(
                f"PredictorConfig.box_size must be one of {BOX_SIZES}, got {self.box_size!r}"
            )
        if self.box_size == "metric" and self.input_dim < FEATURE_DIM:
            raise ValueError(
                f"PredictorConfig.box_size 'metric' needs the altitude feature: input_dim must "
                f"be >= {FEATURE_DIM}, got {self.input_dim}"
            )
        for name in ("past_steps", "future_steps", "input_dim", "d_model", "n_heads", "d_ff"):
            if getattr(self, name) < 1:
                raise ValueError(f"PredictorConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.d_model % self.n_heads:
            raise ValueError(
                f"PredictorConfig.d_model ({self.d_model}) must be a multiple of n_heads "
                f"({self.n_heads})"
            )
        if self.adain and "encoder" in self.adain_sites and self.past_steps < 2:
            raise ValueError(
                "PredictorConfig.adain at the encoder needs past_steps >= 2 (statistics over time)"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"PredictorConfig.dropout must be in [0, 1), got {self.dropout}")

    def to_json(self) -> str:
        """The configuration as a JSON object (see :meth:`from_json`)."""
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> PredictorConfig:
        """The configuration written by :meth:`to_json`; ``ValueError`` naming what is wrong
        (not JSON, an unknown field, a value :meth:`__post_init__` refuses)."""
        try:
            values = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"PredictorConfig: not JSON ({exc})") from None
        if not isinstance(values, dict):
            kind = type(values).__name__
            raise ValueError(f"PredictorConfig: expected a JSON object, got {kind}")
        unknown = set(values) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"PredictorConfig: unknown fields {sorted(unknown)}")
        for name in ("adain_sites", "field_m"):  # JSON has lists, the config tuples
            if name in values:
                values[name] = tuple(values[name])
        return cls(**values)


def predictor_config(
    variant: Variant, past_steps: int = 10, future_steps: int = 5, **overrides: object
) -> PredictorConfig:
    """The configuration of a named variant.

    * ``dronefl``: d_model 16, AdaIN on altitude, positions relative to the drone (the paper's).
    * ``plain``: the same transformer without AdaIN, absolute positions (FL baselines).
    * ``large``: the ``dronefl`` design at d_model 64, ff 128 (the centralized upper bound).
    """
    base = PredictorConfig(past_steps=past_steps, future_steps=future_steps)
    if variant == "dronefl":
        config = base
    elif variant == "plain":
        config = replace(base, adain=False, relative=False)
    elif variant == "large":
        config = replace(base, d_model=64, d_ff=128)
    else:
        raise ValueError(f"unknown predictor variant {variant!r}; choose one of {VARIANTS}")
    return replace(config, **overrides) if overrides else config


def sinusoidal_positions(positions: torch.Tensor, d_model: int) -> torch.Tensor:
    """Vaswani et al. encodings ``PE[p, 2i] = sin(p / 10000^(2i/d))``, ``PE[p, 2i+1] = cos(.)``
    for integer step indices ``positions`` (T,); returns (T, d_model)."""
    i = torch.arange(0, d_model, 2, dtype=torch.float32)
    angle = positions.float()[:, None] / torch.pow(10000.0, i / d_model)[None, :]  # (T, d/2)
    pe = torch.zeros(positions.shape[0], d_model)
    pe[:, 0::2] = torch.sin(angle)
    pe[:, 1::2] = torch.cos(angle[:, : d_model // 2])
    return pe


class AltitudeAdaIN(nn.Module):
    """Adaptive instance normalisation on the drone's altitude (paper Eq. 6).

    For an input ``z`` (B, T, C) and altitude ``h`` (B,) m, with the style
    ``(mu_k, sigma_k)_k = A (h / ALTITUDE_SCALE_M) + b`` (learned ``A``, ``b``)::

        o_k = sigma_k (z_k - mean(z_k)) / std(z_k) + mu_k

    where mean and (population) std are taken over the ``axis`` of one instance: ``time``
    (per channel over the T steps, as SPEC §4 states Eq. 6) or ``channel`` (per step over the C
    channels, a layer norm whose gain and bias are set by the altitude; it needs only one step,
    so it also works with L_f = 1).

    ``init`` ``identity``: ``A = 0``, ``b = (0, 1)``, plain normalisation; ``altitude``:
    ``mu = 0`` and ``sigma = h / ALTITUDE_SCALE_M`` (``A = (0, 1)``, ``b = 0``), so that what
    follows scales with the altitude from the start, as metres on the ground per unit of image
    offset do (the footprint is ``2 h tan(hfov / 2)``).
    """

    def __init__(
        self, channels: int, axis: str = "time", init: str = "identity", eps: float = 1e-5
    ) -> None:
        super().__init__()
        if axis not in ("time", "channel"):
            raise ValueError(f"AltitudeAdaIN axis must be 'time' or 'channel', got {axis!r}")
        if init not in STYLE_INITS:
            raise ValueError(f"AltitudeAdaIN init must be one of {STYLE_INITS}, got {init!r}")
        self.eps = eps
        self.dim = 1 if axis == "time" else 2
        self.style = nn.Linear(1, 2 * channels)
        ones, zeros = torch.ones(channels), torch.zeros(channels)
        with torch.no_grad():
            if init == "identity":
                self.style.weight.zero_()
                self.style.bias.copy_(torch.cat([zeros, ones]))
            else:
                self.style.weight.copy_(torch.cat([zeros, ones])[:, None])
                self.style.bias.zero_()

    def forward(self, z: torch.Tensor, altitude: torch.Tensor) -> torch.Tensor:
        if not torch.jit.is_tracing() and z.shape[self.dim] < 2:  # traced shapes are fixed
            raise ValueError(
                "AltitudeAdaIN needs at least 2 time steps to normalise over time"
                if self.dim == 1
                else "AltitudeAdaIN needs at least 2 channels to normalise over channels"
            )
        h = (altitude / ALTITUDE_SCALE_M).unsqueeze(-1)  # (B, 1)
        mu, sigma = self.style(h).unsqueeze(1).chunk(2, dim=-1)  # (B, 1, C) each
        mean = z.mean(dim=self.dim, keepdim=True)  # (B, 1, C) or (B, T, 1)
        centred = z - mean  # (B, T, C)
        # Population variance written out: torch.var over a short middle axis is ~15x slower.
        var = centred.pow(2).mean(dim=self.dim, keepdim=True)
        return sigma * centred * torch.rsqrt(var + self.eps) + mu


class _LastDimSoftmax(torch.autograd.Function):
    """Softmax over a short last axis. The stock CPU kernel is slow when that axis holds only
    L_p or L_f (5-10) entries (~1.3 ms for a 256-window batch here); this one is a few
    vectorised elementwise ops, with the analytic backward ``y * (g - sum(g * y))``."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, a: torch.Tensor) -> torch.Tensor:
        e = (a - a.amax(dim=-1, keepdim=True)).exp_()
        y = e.div_(e.sum(dim=-1, keepdim=True))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, g: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return y * (g - (g * y).sum(dim=-1, keepdim=True))


def last_dim_softmax(a: torch.Tensor) -> torch.Tensor:
    """Softmax over the last axis; plain tensor ops when no gradient is needed (so that the
    model traces and exports to TorchScript/ONNX), :class:`_LastDimSoftmax` when training."""
    if a.requires_grad:
        return _LastDimSoftmax.apply(a)
    e = (a - a.amax(dim=-1, keepdim=True)).exp()
    return e / e.sum(dim=-1, keepdim=True)


class Attention(nn.Module):
    """Multi-head scaled dot-product attention (self-attention when ``memory`` is None):
    ``softmax(Q K^T / sqrt(d_head)) V`` per head, dropout on the attention weights, as
    ``nn.MultiheadAttention`` (packed ``in_proj`` weights, ``out_proj``)."""

    def __init__(self, d_model: int, n_heads: int, dropout: float) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.d_model = d_model
        self.scale = (d_model // n_heads) ** -0.5
        self.in_proj = nn.Linear(d_model, 3 * d_model)
        self.out_proj = nn.Linear(d_model, d_model)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor | None = None) -> torch.Tensor:
        b, t, _ = x.shape
        c = self.d_model  # a Python int, also when traced for TorchScript/ONNX
        if memory is None:
            q, k, v = self.in_proj(x).split(c, dim=-1)  # 3 x (B, T, C)
        else:
            # Cross-attention: queries from x, keys/values from memory, same packed weights.
            w_q, w_kv = self.in_proj.weight.split([c, 2 * c])
            b_q, b_kv = self.in_proj.bias.split([c, 2 * c])
            q = F.linear(x, w_q, b_q)  # (B, T, C)
            k, v = F.linear(memory, w_kv, b_kv).split(c, dim=-1)  # 2 x (B, S, C)
        hd = c // self.n_heads
        q = q.view(b, t, self.n_heads, hd).transpose(1, 2)  # (B, H, T, hd)
        k = k.view(b, -1, self.n_heads, hd).transpose(1, 2)  # (B, H, S, hd)
        v = v.view(b, -1, self.n_heads, hd).transpose(1, 2)  # (B, H, S, hd)
        weights = last_dim_softmax((q @ k.transpose(-1, -2)) * self.scale)  # (B, H, T, S)
        y = self.drop(weights) @ v  # (B, H, T, hd)
        return self.out_proj(y.transpose(1, 2).reshape(b, t, c))  # (B, T, C)


class FeedForward(nn.Sequential):
    """Position-wise ``Linear(d, d_ff) -> ReLU -> Dropout -> Linear(d_ff, d)``."""

    def __init__(self, d_model: int, d_ff: int, dropout: float) -> None:
        super().__init__(
            nn.Linear(d_model, d_ff), nn.ReLU(), nn.Dropout(dropout), nn.Linear(d_ff, d_model)
        )


class EncoderLayer(nn.Module):
    """Post-norm encoder layer (as ``nn.TransformerEncoderLayer`` with its defaults)."""

    def __init__(self, config: PredictorConfig) -> None:
        super().__init__()
        self.attn = Attention(config.d_model, config.n_heads, config.dropout)
        self.ff = FeedForward(config.d_model, config.d_ff, config.dropout)
        self.norm1 = nn.LayerNorm(config.d_model)
        self.norm2 = nn.LayerNorm(config.d_model)
        self.drop = nn.Dropout(config.dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.norm1(x + self.drop(self.attn(x)))
        return self.norm2(x + self.drop(self.ff(x)))


class DecoderLayer(nn.Module):
    """Post-norm decoder layer (as ``nn.TransformerDecoderLayer`` with its defaults)."""

    def __init__(self, config: PredictorConfig) -> None:
        super().__init__()
        self.self_attn = Attention(config.d_model, config.n_heads, config.dropout)
        self.cross_attn = Attention(config.d_model, config.n_heads, config.dropout)
        self.ff = FeedForward(config.d_model, config.d_ff, config.dropout)
        self.norm1 = nn.LayerNorm(config.d_model)
        self.norm2 = nn.LayerNorm(config.d_model)
        self.norm3 = nn.LayerNorm(config.d_model)
        self.drop = nn.Dropout(config.dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        x = self.norm1(x + self.drop(self.self_attn(x)))
        x = self.norm2(x + self.drop(self.cross_attn(x, memory)))
        return self.norm3(x + self.drop(self.ff(x)))


class TrajectoryTransformer(nn.Module):
    """Predicts the next L_f horizontal positions of one target seen by one drone.

    ``forward(features, altitude)``: ``features`` (B, L_p, F) from
    :mod:`dronefl.models.windows`, ``altitude`` (B,) the drone's mean altitude over the window
    in m; returns (B, L_f, 2) positions in m, relative to the drone at time t when the windows
    were built with ``relative=True`` (else around the field centre).
    """

    #: Name prefix of the output head: the layer FedPer keeps personal.
    HEAD = "head."

    def __init__(self, config: PredictorConfig) -> None:
        super().__init__()
        self.config = config
        d = config.d_model
        self.embed = nn.Linear(config.input_dim, d)
        self.queries = nn.Parameter(0.02 * torch.randn(config.future_steps, d))
        steps = torch.arange(config.past_steps + config.future_steps)
        pe = sinusoidal_positions(steps, d)
        self.register_buffer("pe_past", pe[: config.past_steps].clone(), persistent=False)
        self.register_buffer("pe_future", pe[config.past_steps :].clone(), persistent=False)
        self.encoder = nn.ModuleList(EncoderLayer(config) for _ in range(config.n_encoder_layers))
        self.encoder_adain = config.adain and "encoder" in config.adain_sites
        self.adain = nn.ModuleList(
            AltitudeAdaIN(d) for _ in range(config.n_encoder_layers if self.encoder_adain else 0)
        )
        self.decoder = nn.ModuleList(DecoderLayer(config) for _ in range(config.n_decoder_layers))
        self.head_adain = (
            AltitudeAdaIN(d, axis="channel", init=config.head_style_init)
            if config.adain and "head" in config.adain_sites
            else None
        )
        self.head = nn.Linear(d, 2)
        self.output_scale = config.frame.scale_m  # m per head unit
        self.box_size = config.box_size

    def forward(self, features: torch.Tensor, altitude: torch.Tensor) -> torch.Tensor:
        b, t, f = features.shape
        if not torch.jit.is_tracing() and (t, f) != (self.config.past_steps, self.config.input_dim):
            raise ValueError(
                f"features must have shape (B, {self.config.past_steps}, "
                f"{self.config.input_dim}), got {tuple(features.shape)}"
            )
        if self.box_size != "image":
            features = metric_box(features, self.box_size)
        x = self.embed(features) + self.pe_past  # (B, L_p, d)
        for k, layer in enumerate(self.encoder):
            x = layer(x)
            if self.encoder_adain:
                x = x + self.adain[k](x, altitude)  # (B, L_p, d)
        y = (self.queries + self.pe_future).expand(b, -1, -1)  # (B, L_f, d)
        for layer in self.decoder:
            y = layer(y, x)
        if self.head_adain is not None:
            y = self.head_adain(y, altitude)  # (B, L_f, d), gain and bias set by the altitude
        return self.head(y) * self.output_scale  # (B, L_f, 2) m


def metric_box(features: torch.Tensor, box_size: str = "metric") -> torch.Tensor:
    """``features`` (..., F) with box features multiplied by the altitude feature z / 50 m of
    the same step. ``metric``: width and height, ``w' = w z / 50 m``, in proportion to the
    vehicle's ground width (a box is ``s / (2 h tan(hfov / 2))`` of the image for a vehicle of
    s m). ``ground``: the centre's offset from the image centre too, ``c' = c z / 50 m``, in
    proportion to the target's ground offset from the point below a nadir camera. Missed
    steps stay zero."""
    parts = _METRIC_FEATURES[box_size]
    scale = features[..., ALTITUDE_FEATURE : ALTITUDE_FEATURE + 1]
    return torch.cat(
        [features[..., : parts.start], features[..., parts] * scale, features[..., parts.stop :]],
        dim=-1,
    )


def build_model(config: PredictorConfig, seed: int = 0) -> TrajectoryTransformer:
    """A freshly initialised model; the same ``seed`` gives the same weights."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return TrajectoryTransformer(config)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters (the weights exchanged in FL)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def parameter_summary() -> str:
    """One line per variant with its trainable parameter count."""
    lines = []
    for variant in VARIANTS:
        model = build_model(predictor_config(variant))
        lines.append(f"{variant:8s} {count_parameters(model):7d} parameters")
    return "\n".join(lines)


def describe(config: PredictorConfig) -> str:
    """Short human-readable summary of an architecture."""
    return (
        f"d_model {config.d_model}, {config.n_heads} heads, {config.n_encoder_layers}+"
        f"{config.n_decoder_layers} layers, ff {config.d_ff}, L_p {config.past_steps}, "
        f"L_f {config.future_steps}, adain {config.adain}, box size {config.box_size}, "
        f"relative {config.relative}"
    )
