"""The thesis' published numbers that reports print beside ours, in one place (C. Pinard,
"Robust Learning of a depth map for obstacle avoidance with a monocular stabilized flying
camera", 2019). Each constant names its table; values are copied as printed there.

Where the project uses a number the thesis does not give (e.g. the public code's sample budget),
the constant says so.
"""

from __future__ import annotations

from dataclasses import dataclass

# ---------------------------------------------------------------- chapter 3

#: Tables 3.4 / 3.5 (StillBox validation set, 64 px): MAE (m), MRE, MLE per method, and the
#: public DepthNet repository's 1/4-resolution "depth error" (its README, not the thesis)
TABLE_3_4_64PX = {
    "depthnet": {"mae": 4.72, "mre": 0.26, "mle": 0.32, "depth_error": 4.65},
    "flownets-depth": {"mae": 5.72, "mre": 0.363, "mle": 0.276},
    "flownets-flow": {"mae": 6.462, "mre": 0.203, "mle": 0.172},  # FlowNetS -> depth
}
#: the chapter-3 budget implied by the public DepthNet code's 55 epochs over StillBox-64's
#: 80,000 scenes x 10 frames (one sample per frame); the thesis states neither number
PUBLIC_CODE_SAMPLES = 44_000_000

# ---------------------------------------------------------------- chapter 4

#: Table 4.1: the values each row gives, in this order (κ, λ, M, ΔM, LE Horizon, LE Flower)
TABLE_4_1_KEYS = ("kappa", "lambda", "m", "delta_m", "horizon", "flower")
#: Table 4.1, per smooth loss: (ODM off, ODM on) rows of TABLE_4_1_KEYS
TABLE_4_1: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "tv": ((1, 1, 0.34, 0.45, 0.37, 0.48), (0.1, 1, 0.63, 0.44, 0.36, 0.24)),
    "tvv": ((3, 1, 0.36, 0.31, 0.86, 0.36), (0.3, 0.1, 0.74, 0.15, 0.26, 0.16)),
    "diffusion": ((0.3, 30, 0.67, 0.32, 0.42, 0.16), (0.3, 1, 0.86, 1.05, 0.12, 0.10)),
    "gradient_diffusion": ((0.3, 30, 0.54, 0.11, 0.36, 0.32), (0.3, 0.3, 0.77, 0.15, 0.16, 0.17)),
    "robust_diffusion": ((0.3, 100, 0.69, 0.52, 0.44, 0.12), (1, 1, 0.84, 0.62, 0.07, 0.14)),
    "robust_gradient_diffusion": (
        (0.3, 30, 0.57, 0.23, 0.40, 0.29),
        (0.3, 0.3, 0.77, 0.14, 0.12, 0.20),
    ),
}

# ---------------------------------------------------------------- chapter 5

#: the "no supervision" mark of Tables 5.2 / 5.3 (Table 5.3 prints "-" where Table 5.2 prints ✗)
NONE = "✗"


@dataclass(frozen=True)
class ThesisRow:
    """One row of Table 5.2 (StillBox, no pretraining) or 5.3 (upside-down KITTI, no training
    on it): ``occlusion`` None where the table has no such column; ``values`` in
    core.metrics.THESIS_METRICS' order (MAE, MRE, MLE, SAE, SLE, P1.25, P1.25², P1.25³)."""

    table: str
    method: str
    training_set: str
    scale: str
    supervision: str
    occlusion: bool | None
    values: tuple[float, ...]


#: Tables 5.2 (upright scores) and 5.3 (upside down)
TABLES_5_2_5_3 = (
    ThesisRow("5.2", "Supervised DepthNet", "S", "P", "D + O", False,
              (3.822, 0.224, 0.229, 6.864, 0.446, 0.718, 0.856, 0.927)),
    ThesisRow("5.2", "SFMLearner", "S", "GT", NONE, False,
              (11.429, 0.593, 0.633, 17.173, 0.461, 0.479, 0.656, 0.756)),
    ThesisRow("5.2", "SFMLearner", "S", "P", NONE, False,
              (14.324, 0.816, 0.461, 19.447, 0.726, 0.302, 0.542, 0.696)),
    ThesisRow("5.2", "Unsupervised DepthNet", "S", "P", NONE, False,
              (10.356, 0.437, 0.387, 10.236, 0.516, 0.476, 0.697, 0.822)),
    ThesisRow("5.2", "Unsupervised DepthNet", "S", "P", "O", False,
              (5.248, 0.259, 0.232, 9.600, 0.380, 0.709, 0.887, 0.928)),
    ThesisRow("5.2", "Unsupervised DepthNet", "S", "P", NONE, True,
              (10.412, 0.435, 0.383, 15.450, 0.510, 0.503, 0.716, 0.820)),
    ThesisRow("5.2", "Unsupervised DepthNet", "S", "P", "O", True,
              (5.060, 0.212, 0.206, 9.262, 0.333, 0.729, 0.899, 0.943)),
    ThesisRow("5.3", "Supervised DepthNet", "S", "P", "D + O", None,
              (7.716, 0.637, 0.443, 10.499, 0.548, 0.359, 0.614, 0.774)),
    ThesisRow("5.3", "Constant plane", "-", "GT", "-", None,
              (7.547, 0.458, 0.476, 12.124, 0.600, 0.296, 0.547, 0.752)),
    ThesisRow("5.3", "SFMLearner", "K", "GT", NONE, None,
              (8.433, 0.551, 0.551, 12.469, 0.680, 0.255, 0.482, 0.668)),
    ThesisRow("5.3", "SFMLearner", "K", "P", NONE, None,
              (16.085, 1.511, 0.790, 19.677, 0.927, 0.176, 0.342, 0.494)),
    ThesisRow("5.3", "Unsupervised DepthNet", "S → K", "P", NONE, None,
              (7.759, 0.596, 0.442, 11.250, 0.555, 0.370, 0.628, 0.784)),
    ThesisRow("5.3", "Unsupervised DepthNet", "S → K", "P", "O", None,
              (7.731, 0.604, 0.414, 11.152, 0.536, 0.424, 0.673, 0.807)),
)  # fmt: skip
