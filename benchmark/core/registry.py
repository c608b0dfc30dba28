"""Registered methods: a name → what it predicts, how to build its network, how to train it.

Methods (``MODELS``): DepthNet (depth directly), FlowNetS with a depth head, FlowNetS for optical
flow followed by depth from flow and the known translation (benchmark.core.flow), DepthNet
trained from video without depth with a PoseNet (``depthnet-unsup``, thesis chapter 5; a 6-DoF
PoseNet for rotating data: ``depthnet-unsup-6dof``), its single-frame baseline
(``sfmlearner``: DispNet + PoseNet, depth up to a scale), the same
geometry fed with ground-truth flow (``oracle-flow``) and a constant depth (``constant``); the last
two have no network. ``-tiny`` variants (1/8 width) exist for tests and smoke runs. Each
network's training hyper-parameters are a ``Recipe`` (benchmark.core.config: TrainConfig's recipe
fields, whose defaults are :data:`DEPTH_RECIPE`), and a run of a method starts from that
method's recipe.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import Enum, auto

from torch import nn

from stillbox_gen.conventions import MAX_DEPTH

from .config import Recipe
from .dispnet import SCALES as DISP_SCALES
from .dispnet import SfmLearnerNet
from .models import FLOW_DIV, DepthNet, FlowNetS
from .posenet import DepthPoseNet

#: DepthNet's recipe (SGD, lr 0.01, momentum and dampening 0.9, weight decay 4e-4, batch 256,
#: 55 epochs); depth networks are all trained with it (thesis Table 3.5).
DEPTH_RECIPE = Recipe()

#: The public FlowNetS flow recipe: Adam (lr 1e-4, betas 0.9/0.999, weight decay 4e-4), loss in
#: flow / 20; batch, epochs and lr steps as DepthNet. DepthNet's SGD at lr 0.01 did not learn flow
#: here (64 px, 2 epochs: predictions uncorrelated with the truth, EPE 10.7 px against 3.0 px for
#: zero flow).
FLOW_RECIPE = replace(DEPTH_RECIPE, optimizer="adam", lr=1e-4, loss_scale=1.0 / FLOW_DIV)

#: The clamped DepthNet of thesis 6.4: depth clamped to [10, 60] m, pairs 5 frames apart
#: (instead of 3), so that the network focuses on mid-range depths; made for multi-shift inference.
CLAMPED_RECIPE = replace(DEPTH_RECIPE, shift=5, depth_range=(10.0, 60.0))
THIN_WIDTH = 0.5  # channel multiplier of the thin clamped DepthNet (thesis 6.4: half the maps)

#: DepthNet trained from video without depth (thesis §5.2, §5.4.2): Adam, lr 2e-4, betas
#: (0.9, 0.999), sequences of 5 frames, multi-scale weights 1/2^s (eq. 5.5, finest first), no
#: learning-rate steps (the thesis gives none); no weight decay (the thesis adds "classic L2
#: regularisation" to eq. 5.2 without a value; the author's code defaults to 0): with Adam, L2 is
#: added to the gradient before its normalisation, and DepthNet's 4e-4·|w| exceeded the
#: photometric gradient for half of a supervised DepthNet's weights (64 px StillBox, batch 16),
#: where Adam's steps would shrink the weights by about lr/|w| ≈ 1 % a step whatever the loss.
#: Batch 32 and 20 epochs are this project's CPU budget (the thesis trained about 10 hours on a
#: GPU).
UNSUPERVISED_RECIPE = replace(
    DEPTH_RECIPE,
    optimizer="adam",
    lr=2e-4,
    momentum=0.9,
    beta2=0.999,
    batch_size=32,
    epochs=20,
    milestones=(),
    weight_decay=0.0,
    loss_weights=tuple(1 / 2**s for s in range(5)),
    sequence_length=5,
    pose="translation",
)
#: The same with a 6-DoF PoseNet (rotating data, thesis §5.2.1-5.2.2: its rotation stabilises
#: the reference before DepthNet and warps every frame)
UNSUPERVISED_6DOF_RECIPE = replace(UNSUPERVISED_RECIPE, pose="6dof")

#: The SFMLearner baseline (thesis §5.4, Zhou et al. 2017): depthnet-unsup's recipe and losses,
#: with DispNet's 4 scales (weights 1/2^s, finest first)
SFMLEARNER_RECIPE = replace(
    UNSUPERVISED_RECIPE, loss_weights=tuple(1 / 2**s for s in range(DISP_SCALES))
)


class Target(Enum):
    """What a method's network learns and outputs (the value: data.PairDataset's ``target``)."""

    DEPTH = "depth"  # metres, multi-scale list as DepthNet; multi-scale L1 loss
    FLOW = "flow"  # pixels of the input resolution, multi-scale list; multi-scale EPE loss
    VIDEO = "video"  # depth (metres at the nominal displacement) learnt from frame sequences
    # without ground truth: photometric + smooth loss (benchmark.unsupervised.training)


class Scoring(Enum):
    """How a method's depth is obtained when it is scored (evaluate.predict)."""

    DEPTH = auto()  # the network's depth × |pair translation| / nominal displacement
    FLOW = auto()  # depth from the network's flow and the known translation (core.flow)
    EXACT_FLOW = auto()  # the same geometry fed with the exact (ground-truth) flow
    CONSTANT = auto()  # the training split's median depth at every pixel
    SCALE_FREE = auto()  # depth up to a scale: × |pair translation| / |PoseNet's| ("P"), and
    # × median(ground truth) / median(prediction) per image ("GT", reported beside it)
    GIVEN = auto()  # depth maps read from files (another method's predictions), as given


@dataclass(frozen=True)
class Kind:
    """What a kind of method outputs, whether it trains and how it is scored.

    ``name``: summary.json's ``output``; ``target``: what its network learns (None: no network,
    nothing to build, train or load); ``scored_as``: how its depth is obtained when scored;
    ``best_by``: the validation metric (a key of evaluate's summary) that picks ``best.pt``
    (None without training).
    """

    name: str
    target: Target | None
    scored_as: Scoring
    best_by: str | None = None

    @property
    def trains(self) -> bool:
        """A network, trained by engine.train.Trainer and saved in checkpoints."""
        return self.target is not None


DEPTH = Kind("depth", Target.DEPTH, Scoring.DEPTH, best_by="mae")
FLOW = Kind("flow", Target.FLOW, Scoring.FLOW, best_by="epe")
#: depth learnt without ground truth, scored as DEPTH (best.pt: the validation MAE against the
#: ground truth, where the dataset has it; the loss never sees it)
UNSUPERVISED = Kind("unsupervised-depth", Target.VIDEO, Scoring.DEPTH, best_by="mae")
#: depth up to a scale learnt without ground truth (SFMLearner), scored as SCALE_FREE (best.pt:
#: the validation MAE with the "P" scale, the one a user without ground truth has; the "GT"
#: median scale would hide PoseNet's scale errors)
SCALE_FREE = Kind("scale-free-depth", Target.VIDEO, Scoring.SCALE_FREE, best_by="mae")
ORACLE_FLOW = Kind("oracle-flow", None, Scoring.EXACT_FLOW)
CONSTANT = Kind("constant", None, Scoring.CONSTANT)
#: another method's depth maps, read from files (eval --predictions)
PREDICTIONS = Kind("given-depth", None, Scoring.GIVEN)
#: every kind of method: a depth network (supervised or not, metric or up to a scale), a flow
#: network (depth by geometry), no network, or another method's files
KINDS = (DEPTH, FLOW, UNSUPERVISED, SCALE_FREE, ORACLE_FLOW, CONSTANT, PREDICTIONS)

TINY_WIDTH = 0.125  # channel multiplier of the -tiny variants


@dataclass(frozen=True)
class ModelSpec:
    """A registered method.

    ``build()`` returns a freshly initialised network, or is None for methods without one
    (``oracle-flow``, ``constant``: nothing to train). ``kind`` says what it outputs, whether it
    trains and how its depth is scored (:class:`Kind`: DEPTH, FLOW, ORACLE_FLOW, CONSTANT).
    ``recipe``: its training hyper-parameters (None without a network).
    """

    name: str
    description: str
    build: Callable[[], nn.Module] | None
    kind: Kind = DEPTH
    recipe: Recipe | None = DEPTH_RECIPE

    def __post_init__(self) -> None:
        if (self.build is not None) != self.kind.trains or (self.recipe is None) == self.trainable:
            raise ValueError(f"{self.name}: a network, a recipe and a training kind go together")

    @property
    def trainable(self) -> bool:
        """A network to build and train (its kind trains)."""
        return self.kind.trains


def _specs() -> list[ModelSpec]:
    tiny = "at 1/8 width, for tests and smoke runs"
    return [
        ModelSpec(
            "depthnet",
            "DepthNet (FlowNetS at half width, BN, 1+ELU depth output), ~10.3 M parameters",
            lambda: DepthNet(width=1.0),
        ),
        ModelSpec("depthnet-tiny", f"DepthNet {tiny}", lambda: DepthNet(width=TINY_WIDTH)),
        ModelSpec(
            "depthnet-clamped",
            "DepthNet trained on depth clamped to [10, 60] m with shift 5 (thesis 6.4)",
            lambda: DepthNet(width=1.0),
            recipe=CLAMPED_RECIPE,
        ),
        ModelSpec(
            "depthnet-clamped-thin",
            "depthnet-clamped with half the feature maps (thesis 6.4's thin network)",
            lambda: DepthNet(width=THIN_WIDTH),
            recipe=CLAMPED_RECIPE,
        ),
        ModelSpec(
            "depthnet-clamped-tiny",
            f"depthnet-clamped {tiny}",
            lambda: DepthNet(width=TINY_WIDTH),
            recipe=CLAMPED_RECIPE,
        ),
        ModelSpec(
            "flownets-depth",
            "FlowNetS (BN) with a 1-channel 1+ELU depth output, trained like DepthNet",
            lambda: FlowNetS("depth", batch_norm=True),
        ),
        ModelSpec(
            "flownets-depth-tiny",
            f"flownets-depth {tiny}",
            lambda: FlowNetS("depth", width=TINY_WIDTH, batch_norm=True),
        ),
        ModelSpec(
            "flownets-flow",
            "FlowNetS (BN) for optical flow; depth from flow and the known translation",
            lambda: FlowNetS("flow", batch_norm=True),
            FLOW,
            FLOW_RECIPE,
        ),
        ModelSpec(
            "flownets-flow-tiny",
            f"flownets-flow {tiny}",
            lambda: FlowNetS("flow", width=TINY_WIDTH, batch_norm=True),
            FLOW,
            FLOW_RECIPE,
        ),
        ModelSpec(
            "depthnet-unsup",
            "DepthNet + PoseNet (3 translations) trained from 5-frame sequences without depth "
            "(thesis 5.2)",
            lambda: DepthPoseNet(UNSUPERVISED_RECIPE.sequence_length),
            UNSUPERVISED,
            UNSUPERVISED_RECIPE,
        ),
        ModelSpec(
            "depthnet-unsup-tiny",
            f"depthnet-unsup {tiny}",
            lambda: DepthPoseNet(UNSUPERVISED_RECIPE.sequence_length, TINY_WIDTH),
            UNSUPERVISED,
            UNSUPERVISED_RECIPE,
        ),
        ModelSpec(
            "sfmlearner",
            "SFMLearner baseline: single-frame DispNet + PoseNet (3 translations) trained like "
            "depthnet-unsup without pose normalisation; depth scaled by PoseNet or GT median",
            lambda: SfmLearnerNet(SFMLEARNER_RECIPE.sequence_length),
            SCALE_FREE,
            SFMLEARNER_RECIPE,
        ),
        ModelSpec(
            "sfmlearner-tiny",
            f"sfmlearner {tiny}",
            lambda: SfmLearnerNet(SFMLEARNER_RECIPE.sequence_length, TINY_WIDTH),
            SCALE_FREE,
            SFMLEARNER_RECIPE,
        ),
        ModelSpec(
            "depthnet-unsup-6dof",
            "depthnet-unsup with a 6-DoF PoseNet, for rotating data (thesis 5.2.2)",
            lambda: DepthPoseNet(UNSUPERVISED_6DOF_RECIPE.sequence_length, dof=6),
            UNSUPERVISED,
            UNSUPERVISED_6DOF_RECIPE,
        ),
        ModelSpec(
            "depthnet-unsup-6dof-tiny",
            f"depthnet-unsup-6dof {tiny}",
            lambda: DepthPoseNet(UNSUPERVISED_6DOF_RECIPE.sequence_length, TINY_WIDTH, dof=6),
            UNSUPERVISED,
            UNSUPERVISED_6DOF_RECIPE,
        ),
        ModelSpec(
            "oracle-flow",
            "ground-truth flow -> depth by the FOE geometry (checks geometry vs metadata)",
            None,
            ORACLE_FLOW,
            None,
        ),
        ModelSpec(
            "constant",
            "the training set's median depth at every pixel (the floor to beat)",
            None,
            CONSTANT,
            None,
        ),
    ]


MODELS: dict[str, ModelSpec] = {spec.name: spec for spec in _specs()}


def output_clamp(depth_range) -> tuple[float, float] | None:
    """The range a depth network's outputs are clamped to where it is used: its training
    ``depth_range`` (metres) when narrower than DepthNet's [0, MAX_DEPTH] (a clamped DepthNet),
    else None (outputs used as they are, as the original code does)."""
    lo, hi = (float(v) for v in depth_range)
    return None if (lo, hi) == (0.0, MAX_DEPTH) else (lo, hi)


def list_models() -> list[str]:
    """Registered model names, sorted."""
    return sorted(MODELS)


def build_model(name: str) -> nn.Module:
    """A freshly initialised network by registry name; ValueError for an unknown name or a
    method without a network (oracle-flow, constant)."""
    try:
        spec = MODELS[name]
    except KeyError:
        raise ValueError(
            f"unknown model {name!r}; registered models: {', '.join(list_models())}"
        ) from None
    if spec.build is None:
        raise ValueError(f"{name!r} has no network (nothing to build or train)")
    return spec.build()
