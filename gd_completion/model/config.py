"""GGDConfig: every size of the Graph-Guided Deformation network, serialisable into checkpoints."""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

_TUPLE_FIELDS = ("encoder_h0", "encoder_h1", "encoder_fractions", "code_hidden", "tree_arity",
                 "tree_hidden", "local_widths", "ball_scales", "refiner_widths", "refiner_hidden")


@dataclass(frozen=True)
class GGDConfig:
    """All hyper-parameters of GGDNet (defaults: the shipped vehicle model, see docs/MODEL.md)."""

    num_input: int = 1024            # N, input points per vehicle
    num_output: int = 2048           # N_o, completion points
    num_control: int = 256           # N_c, FPS control points taken from the input
    # generation branch: multi-resolution PointNet encoder
    encoder_h0: tuple[int, ...] = (64, 128)     # shared point MLP h0 (Linear-BN-ReLU)
    encoder_h1: tuple[int, ...] = (256,)        # point MLP h1, one per resolution
    encoder_fractions: tuple[int, ...] = (1, 2, 8)  # resolutions N/1, N/2, N/8 (nested FPS prefixes)
    code_hidden: tuple[int, ...] = (512,)       # MLP from the concatenated features to the code
    code_dim: int = 256                          # f_final
    # TopNet-style tree decoder: prod(tree_arity) == num_output - num_control
    tree_arity: tuple[int, ...] = (8, 8, 4, 7)
    tree_node_dim: int = 16
    tree_hidden: tuple[int, ...] = (128, 64)
    # a learned linear shape basis added to the tree's points: P_s += sum_k c_k(code) T_k, T_k (N_s, 3) parameters
    # (0: none, the paper's decoder; a probe of issue 32's point 3, docs/MODEL.md "A learned shape basis")
    shape_basis: int = 0
    # local features: ball grouping of input points around each point of P_g
    radius: float = 0.05                         # r in the normalised frame (vehicle length = 1)
    ball_scales: tuple[int, ...] = (1, 2, 4)     # radii r, 2r, 4r (ball s*r drawn from N/s^2 FPS points)
    ball_m: int = 8                              # M points per ball
    local_widths: tuple[int, ...] = (32, 32)     # shared Linear-BN-ReLU on relative coordinates
    # graph deformation (G-ResNet)
    knn_k: int = 8
    knn_margin: float = 0.08                     # x-window margin of the kNN search (exact within it)
    window_search: bool = True                   # x-sorted window search (else brute force, O(N^2))
    gcn_width: int = 64
    gcn_blocks: int = 2
    offset_init_gain: float = 0.1                # small initial offsets: P_o starts near P_g
    # conditioning on the box shape (width/length, height/length), a deviation from the paper (docs/MODEL.md)
    box_conditioning: bool = False
    # local features also group the input's mirror image (y -> -y): the deformation sees the likely unseen side
    mirror_local_features: bool = False
    # a BoxRefiner first estimates the true box in the given box's frame; the network completes in that frame
    # and maps its points back (needs box_conditioning; docs/MODEL.md, "Box refinement")
    box_refinement: bool = False
    refiner_widths: tuple[int, ...] = (64, 128, 256)  # its shared point MLP (Conv1d-BN-ReLU)
    refiner_hidden: tuple[int, ...] = (256, 128)      # its MLP from the pooled code and the box shape

    def __post_init__(self) -> None:
        for name in _TUPLE_FIELDS:
            object.__setattr__(self, name, tuple(int(v) for v in getattr(self, name)))
        problems = []
        if self.num_control < 1 or self.num_control > self.num_input:
            problems.append(f"num_control={self.num_control} must be in [1, num_input={self.num_input}]")
        n_s = self.num_output - self.num_control
        if n_s < 1 or math.prod(self.tree_arity) != n_s:
            problems.append(f"prod(tree_arity)={math.prod(self.tree_arity)} must equal "
                            f"num_output - num_control = {n_s}")
        if len(self.tree_arity) < 2:
            problems.append("tree_arity needs at least 2 levels")
        if len(self.encoder_h0) < 1 or len(self.encoder_h1) < 1 or len(self.local_widths) < 1:
            problems.append("encoder_h0, encoder_h1 and local_widths need at least one layer")
        if any(f < 1 for f in self.encoder_fractions) or any(s < 1 for s in self.ball_scales):
            problems.append("encoder_fractions and ball_scales must be >= 1")
        if self.num_input // max(self.encoder_fractions) < 1:
            problems.append("num_input too small for encoder_fractions")
        if self.radius <= 0 or self.ball_m < 1 or self.knn_k < 1 or self.gcn_width < 1 or self.gcn_blocks < 0:
            problems.append("radius, ball_m, knn_k, gcn_width must be positive, gcn_blocks >= 0")
        if self.shape_basis < 0:
            problems.append("shape_basis must be >= 0")
        if self.knn_k >= self.num_output:
            problems.append("knn_k must be < num_output")
        if not self.refiner_widths or min(self.refiner_widths + self.refiner_hidden) < 1:
            problems.append("refiner_widths needs at least one layer and every refiner width must be positive")
        if self.box_refinement and not self.box_conditioning:
            problems.append("box_refinement needs box_conditioning (the refiner reads the box shape)")
        if problems:
            raise ValueError("invalid GGDConfig: " + "; ".join(problems))

    @property
    def num_coarse(self) -> int:
        """N_s, points produced by the tree decoder."""
        return self.num_output - self.num_control

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (ints, floats, lists) for checkpoints and logs."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> GGDConfig:
        """Inverse of `to_dict`; raises ValueError on unknown keys or invalid values."""
        if not isinstance(data, dict):
            raise ValueError(f"config must be a dict, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown GGDConfig keys: {unknown}")
        return cls(**data)
