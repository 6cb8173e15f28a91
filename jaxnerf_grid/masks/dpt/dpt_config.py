"""The DPT configuration: the subset of Hugging Face's DPTConfig that the ViT-based DPT uses,
plus which heads the model carries (an HF checkpoint has one; the built-in model has both)."""

from __future__ import annotations

import dataclasses

from jaxnerf_grid.config.schema import ConfigError

HEADS = ("segmentation", "depth")
READOUTS = ("ignore", "add", "project")


@dataclasses.dataclass(frozen=True)
class DPTConfig:
    """Hashable (usable as a jit static argument). Field names follow HF's DPTConfig."""

    hidden_size: int = 768
    num_hidden_layers: int = 12
    num_attention_heads: int = 12
    intermediate_size: int = 3072
    layer_norm_eps: float = 1e-12
    image_size: int = 384          # the grid the position embeddings were trained at (square)
    patch_size: int = 16
    num_channels: int = 3
    qkv_bias: bool = True
    backbone_out_indices: tuple = (2, 5, 8, 11)
    readout_type: str = "project"
    reassemble_factors: tuple = (4, 2, 1, 0.5)
    neck_hidden_sizes: tuple = (96, 192, 384, 768)
    fusion_hidden_size: int = 256
    head_in_index: int = -1
    use_batch_norm_in_fusion_residual: bool = False
    use_bias_in_fusion_residual: bool | None = None
    add_projection: bool = False
    use_auxiliary_head: bool = True
    num_labels: int = 150
    heads: tuple = ("segmentation",)
    id2label: tuple = ()           # label names by id (may be empty)

    def __post_init__(self):
        for f in dataclasses.fields(self):  # JSON gives lists; keep the config hashable
            v = getattr(self, f.name)
            if isinstance(v, list):
                object.__setattr__(self, f.name, tuple(v))
        validate(self)

    @property
    def fusion_bias(self) -> bool:
        """HF's rule: residual-conv bias unless batch norm, unless set explicitly."""
        if self.use_bias_in_fusion_residual is None:
            return not self.use_batch_norm_in_fusion_residual
        return bool(self.use_bias_in_fusion_residual)

    @property
    def num_positions(self) -> int:
        return (self.image_size // self.patch_size) ** 2 + 1


def validate(cfg: DPTConfig) -> None:
    """Raises ConfigError naming the field that makes the configuration unusable."""
    if cfg.readout_type not in READOUTS:
        raise ConfigError(f"dpt config: readout_type {cfg.readout_type!r} not in {READOUTS}")
    if not cfg.heads or any(h not in HEADS for h in cfg.heads):
        raise ConfigError(f"dpt config: heads {cfg.heads!r} must be a non-empty subset of {HEADS}")
    if cfg.hidden_size % cfg.num_attention_heads:
        raise ConfigError(f"dpt config: hidden_size {cfg.hidden_size} is not a multiple of "
                          f"num_attention_heads {cfg.num_attention_heads}")
    n = len(cfg.neck_hidden_sizes)
    if len(cfg.reassemble_factors) != n or len(cfg.backbone_out_indices) != n:
        raise ConfigError("dpt config: backbone_out_indices, reassemble_factors and neck_hidden_sizes "
                          f"must have the same length, got {len(cfg.backbone_out_indices)}, "
                          f"{len(cfg.reassemble_factors)}, {n}")
    for i in cfg.backbone_out_indices:
        if not 0 <= i < cfg.num_hidden_layers:
            raise ConfigError(f"dpt config: backbone_out_indices entry {i} outside 0..{cfg.num_hidden_layers - 1}")
    for f in cfg.reassemble_factors:
        if f not in (4, 2, 1, 0.5) and not (f > 1 and float(f).is_integer()):
            raise ConfigError(f"dpt config: reassemble factor {f} unsupported (integer >= 1 or 0.5)")
    if cfg.add_projection and cfg.fusion_hidden_size != 256:
        raise ConfigError("dpt config: add_projection needs fusion_hidden_size 256 (HF hard-codes it)")
    if "segmentation" in cfg.heads and cfg.num_labels < 1:
        raise ConfigError("dpt config: num_labels must be >= 1 for a segmentation head")
    if cfg.image_size % cfg.patch_size:
        raise ConfigError(f"dpt config: image_size {cfg.image_size} not a multiple of patch_size {cfg.patch_size}")
