"""``stillbox-bench eval-sequences``: depth networks trained without depth scored the thesis'
way (§5.4.3-5.4.4, Tables 5.2-5.3); the command's run and tables: sequence_report.

Every window of :data:`SEQUENCE_LENGTH` consecutive frames of each scene of a split (PoseNet's
input length, 5) is one test sample: the depth of its *last* frame t is scored against t's
ground truth (benchmark.core.metrics: predictions clamped to [0.1, 100] m, ground truth clipped
to 100 m, per image, then the mean over images).

- DepthNet (supervised ``depthnet*``, ``depthnet-unsup*``) reads the pairs (r, t) for each of the
  4 earlier frames r, each reference stabilised to t's orientation first (eq. 5.1,
  benchmark.unsupervised.rotation.Stabiliser): with the dataset's known orientation (the "O"
  setting; every network but the 6-DoF ones, a supervised DepthNet's "D + O") or with PoseNet's
  rotation (``depthnet-unsup-6dof*``); stabilised scenes are read as they are. The pair kept is
  the one whose mean DepthNet output (finest scale, metres at the nominal displacement d0) is
  closest to :data:`PAIR_TARGET_DEPTH` (§5.4.3), and its output is rescaled by the measured
  displacement, × ‖t_pair‖ / d0 (the "P" scale). Beside it, "P (fixed pair)": the same with the
  reference whose measured displacement is closest to d0, so that a reader sees how much of a
  score is the thesis' rule. A network with a narrower depth range has its
  outputs clamped to it first (registry.output_clamp), as ``eval`` does. The rule reads the
  mean of what the network outputs, saturated or not: a perfect DepthNet scores zero with
  either rule, but one that saturates at 100 m at d0 (the supervised recipe clips its targets
  there) is, on near scenes, kept on a pair shorter than d0 whose far pixels saturate (MAE
  about 13 m on the tests' rotating scene; "P (fixed pair)": zero):
  tests/test_sequence_protocol.py.
- SFMLearner (``sfmlearner*``) reads t alone; its scale-free depth is put in metres by
  benchmark.engine.scaling: "P", the measured displacement over PoseNet's between the
  window's first and last frames (the longest baseline of the window: our choice, the thesis
  does not say which pair), and "GT", the per-image median ratio.
- The constant plane (Table 5.3): every pixel at the median of the image's ground truth ("GT").

Beside the depth, every row of a network with a PoseNet (trained from video: ``depthnet-unsup*``,
``sfmlearner*``) says whether PoseNet found the direction of the camera's motion:
:data:`POSE_COSINE`, the mean over the sequences of the cosine between PoseNet's translation from
t to the row's reference and the true one (:func:`pose_cosines`), and :data:`POSE_COSINE_SHARE`,
the share of sequences whose cosine is above :data:`POSE_COSINE_GOOD`. The reference is the pair
the row's depth came from (DepthNet: the pair each rule kept; SFMLearner, both scales: the
window's first frame, whose displacement "P" reads). Rows without a PoseNet have None there.

``upside_down`` (Table 5.3's robustness test, sky down) scores the same windows with the rows
of every frame and depth map flipped, the camera geometry flipped with them (:func:`upside_down`).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from stillbox_gen.conventions import MAX_DEPTH
from stillbox_gen.dataset import Scene

from ..core import metrics, registry
from ..core.checkpoint import load_checkpoint, load_weights, source_error
from ..core.data import NORM_MEAN, NORM_STD, read_scenes
from ..core.errors import FieldError
from ..engine.scaling import pose_scale
from .rotation import Stabiliser, target_rotations
from .training import compensate

#: frames of a test window: PoseNet's input length (§5.4.3), the recipe's sequence length
SEQUENCE_LENGTH = registry.UNSUPERVISED_RECIPE.sequence_length
#: metres: the pair kept is the one whose mean DepthNet output is closest to this (§5.4.3,
#: "an arbitrary chosen value set to 50 m, regardless of the dataset")
PAIR_TARGET_DEPTH = 50.0
#: where the rotation stabilising DepthNet's reference comes from
STABILISE_KNOWN, STABILISE_POSENET, STABILISE_NONE = "known", "posenet", "none"
#: scale factors: PoseNet's or the measured displacement ("P"), the ground-truth median ("GT");
#: DepthNet's "P" also with a fixed pair: the reference whose measured displacement is closest
#: to the network's nominal one, whatever its output (the thesis' rule picks by the output)
SCALE_P, SCALE_GT, SCALE_P_FIXED = "P", "GT", "P (fixed pair)"
UPRIGHT, UPSIDE_DOWN = "upright", "upside-down"
#: the flip of the camera's y axis (OpenCV axes: y down)
FLIP_Y = np.diag([1.0, -1.0, 1.0])
#: result columns of PoseNet's translation direction (module doc): the mean cosine, and the share
#: of sequences whose cosine is above POSE_COSINE_GOOD
POSE_COSINE, POSE_COSINE_GOOD = "pose_cosine", 0.9
POSE_COSINE_SHARE = f"{POSE_COSINE}_gt_{POSE_COSINE_GOOD:g}"


@dataclass(frozen=True)
class Window:
    """One test sample: ``frames`` (N, H, W, 3) uint8, oldest first; ``depth`` (H, W) metres,
    the last frame's ground truth; ``K`` (3, 3) pixels; ``rotation`` (N, 3, 3): ``R_{t→i}``
    from the last frame's camera axes to frame i's (identity when stabilised); ``position``
    (N, 3): camera i's centre in the last frame's axes, metres; ``stabilised``: every rotation
    is the identity; ``scene``, ``last``: the scene index and the last frame's index."""

    frames: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    rotation: np.ndarray
    position: np.ndarray
    stabilised: bool
    scene: int
    last: int

    @property
    def translation(self) -> np.ndarray:
        """(N, 3) metres: ``τ_i`` with ``X_i = R_{t→i}·X_t + τ_i`` (PoseNet's and the warps'
        convention, in frame i's axes), from camera i's centre ``p_i = −R_{t→i}ᵀ·τ_i``: on a
        stabilised window ``−p_i``, finetune.pose_cosine's known translation."""
        return -np.einsum("nij,nj->ni", self.rotation, self.position)


def scene_windows(scene: Scene, length: int = SEQUENCE_LENGTH) -> list[Window]:
    """Every window of ``length`` consecutive frames of ``scene`` (the last frame t from
    ``length - 1`` to the scene's last), from its frames, depth and poses."""
    frames = np.stack([scene.load_rgb(f) for f in range(scene.frames)])
    out = []
    for t in range(length - 1, scene.frames):
        first = t - length + 1
        poses = [scene.relative_pose(t, i) for i in range(first, t + 1)]  # X_i = R·X_t + τ
        rotation = np.stack([p[:3, :3] for p in poses])
        position = np.stack([-p[:3, :3].T @ p[:3, 3] for p in poses])  # camera i: −Rᵀτ
        depth, K = scene.load_depth(t), np.asarray(scene.K, np.float64)
        window = Window(frames[first : t + 1], depth, K, rotation, position, scene.stabilised,
                        scene.index, t)  # fmt: skip
        out.append(window)
    return out


def upside_down(w: Window) -> Window:
    """The window turned upside down (sky down): rows of every frame and of the depth flipped,
    and the camera geometry with them: the image row y becomes H − 1 − y (pixel-centre
    convention), so ``c_y`` becomes H − 1 − c_y (unchanged when centred), every 3-D point
    (x, y, z) becomes (x, −y, z) (F = diag(1, −1, 1)), positions F·p and rotations F·R·F."""
    h = w.depth.shape[0]
    K = w.K.copy()
    K[1, 2] = h - 1 - K[1, 2]
    return replace(
        w,
        frames=np.ascontiguousarray(w.frames[:, ::-1]),
        depth=np.ascontiguousarray(w.depth[::-1]),
        K=K,
        rotation=FLIP_Y @ w.rotation @ FLIP_Y,
        position=w.position @ FLIP_Y,
    )


def choose_pair(means: torch.Tensor, target: float = PAIR_TARGET_DEPTH) -> int:
    """The index of the pair whose value (metres: its mean output, or its displacement) is
    closest to ``target`` (the first of equally close ones)."""
    return int((means.double() - target).abs().argmin())


@dataclass
class EvalModel:
    """A method as scored here: ``net`` (None: the constant plane), its registry ``name``,
    ``kind`` (registry.Kind), ``d0`` (metres its DepthNet answers for), ``clamp`` (outputs
    clamped to it, or None), ``pose`` (its training's ``--pose``, None without PoseNet),
    ``occlusion``, ``training_set`` and ``checkpoint`` (text for the tables), ``camera`` (its
    training frames' ``width`` and ``height``, pixels, when the checkpoint records them)."""

    name: str
    kind: registry.Kind
    net: torch.nn.Module | None = None
    d0: float = 1.0
    clamp: tuple[float, float] | None = None
    pose: str | None = None
    occlusion: bool = False
    training_set: str = "-"
    checkpoint: str = ""
    camera: dict | None = None

    @property
    def posenet(self) -> bool:
        """The network has a PoseNet (it was trained from video: ``depthnet-unsup*``,
        ``sfmlearner*``; ``net.pose`` gives the poses of a sequence)."""
        return self.net is not None and self.kind.target is registry.Target.VIDEO

    @property
    def stabilise(self) -> str:
        """Where the reference's rotation comes from: PoseNet's (6-DoF networks), none
        (single-frame networks, the constant plane), else the known orientation."""
        if self.kind.scored_as is not registry.Scoring.DEPTH:
            return STABILISE_NONE
        return STABILISE_POSENET if self.pose == "6dof" else STABILISE_KNOWN

    @property
    def scales(self) -> tuple[str, ...]:
        if self.kind.scored_as is registry.Scoring.SCALE_FREE:
            return (SCALE_P, SCALE_GT)
        return (SCALE_GT,) if self.net is None else (SCALE_P, SCALE_P_FIXED)


def constant_plane() -> EvalModel:
    """Table 5.3's constant plane: the image's ground-truth median everywhere."""
    return EvalModel("constant", registry.CONSTANT)


def load_model(path: Path, field: str = "ckpt") -> EvalModel:
    """A depth checkpoint as an :class:`EvalModel` (network in eval mode, on the CPU); a flow
    network's is refused (ValueError of one line naming ``field`` and the file)."""
    ck = load_checkpoint(path, field)
    name = ck["model_name"]
    kind = registry.MODELS[name].kind
    if kind.scored_as not in (registry.Scoring.DEPTH, registry.Scoring.SCALE_FREE):
        raise source_error(field, path, f"'{name}' predicts {kind.name}, not depth")
    net = registry.build_model(name)
    load_weights(net, ck, field, path, name)
    cfg = ck.get("config") or {}
    data, pretrained = cfg.get("data"), cfg.get("pretrained")
    training_set = Path(str(data)).name if data else "?"
    return EvalModel(
        name, kind, net.eval(), float(ck["nominal_displacement"]),
        registry.output_clamp(ck.get("depth_range", (0.0, MAX_DEPTH))),
        cfg.get("pose") if kind.target is registry.Target.VIDEO else None,
        bool(cfg.get("occlusion")),
        f"pretrained → {training_set}" if pretrained else training_set, str(path),
        ck.get("camera"),
    )  # fmt: skip


def _normalised(frames: np.ndarray, device: torch.device) -> torch.Tensor:
    """(N, H, W, 3) uint8 -> (N, 3, H, W) float32, DepthNet's (x/255 − 0.5)/0.2."""
    x = torch.from_numpy(np.ascontiguousarray(frames)).permute(0, 3, 1, 2).float()
    return ((x / 255.0 - NORM_MEAN) / NORM_STD).to(device)


def _full(depth: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(1, 1, h', w') -> (H, W) metres (bilinear, as benchmark.core.metrics.upsample_to)."""
    return metrics.upsample_to(depth, h, w)[0]


@torch.inference_mode()
def predict(m: EvalModel, w: Window, device: torch.device) -> dict:
    """The last frame's depth (H, W) metres for each of ``m.scales`` (``{scale: depth}``),
    ``shifts``: ``{scale: frames between the reference used and t}`` (DepthNet's; empty
    otherwise), and ``pose_cosine``: ``{scale: cosine}`` (:func:`pose_cosines` at the scale's
    reference; empty without PoseNet)."""
    gt = torch.from_numpy(np.ascontiguousarray(w.depth)).to(device)
    if m.net is None:  # the constant plane, at the ground truth's median
        median = metrics.median_scale(torch.ones_like(gt)[None], gt[None])[0]
        return {SCALE_GT: torch.full_like(gt, float(median)), "shifts": {}, "pose_cosine": {}}
    seq = _normalised(w.frames, device)  # (N, 3, H, W)
    n, _, h, wd = seq.shape
    poses = m.net.pose(seq.reshape(1, 3 * n, h, wd)).float() if m.posenet else None
    if m.kind.scored_as is registry.Scoring.SCALE_FREE:
        out = _scale_free(m, w, seq, gt, poses)
    else:
        out = _depthnet(m, w, seq, poses)
    refs = out.pop("references")
    out["pose_cosine"] = {}
    if poses is not None:
        cosines = pose_cosines(m, w, poses, list(refs.values())).tolist()
        out["pose_cosine"] = dict(zip(refs, cosines, strict=True))
    return out


def posenet_translations(m: EvalModel, w: Window, poses: torch.Tensor) -> torch.Tensor:
    """PoseNet's translations from t (the window's last frame) to every frame, ``(N, 3)``:
    ``τ_i`` with ``X_i = R_{t→i}·X_t + τ_i`` in PoseNet's unit, from its ``poses`` ``(1, N,
    dof)`` as training makes them: training.compensate with the rotations of the network's
    ``--pose`` (rotation.target_rotations: none, the window's known ``R_{t→i}`` or PoseNet's
    6-DoF ones). t being the last frame, whose PoseNet row is zero, that is PoseNet's output."""
    tgt = torch.tensor([poses.shape[1] - 1], device=poses.device)
    known = torch.from_numpy(w.rotation).to(poses)[None]
    rotations = target_rotations(m.pose or "translation", poses, known, tgt)
    return compensate(poses[..., :3], tgt, rotations)[0]


def pose_cosines(
    m: EvalModel, w: Window, poses: torch.Tensor, references: list[int]
) -> torch.Tensor:
    """``(len(references),)``: the cosine between PoseNet's translation from t to each reference
    (:func:`posenet_translations`) and the true one (:attr:`Window.translation`), both ``τ_r``
    of ``X_r = R_{t→r}·X_t + τ_r`` in frame r's axes: 1 when PoseNet found the direction,
    whatever its unit; its rotation (6-DoF) does not enter. With the known rotation, the cosine
    of the camera displacements in t's axes (a rotation keeps cosines)."""
    ours = posenet_translations(m, w, poses)[references]
    true = torch.from_numpy(w.translation[references]).to(ours)
    return torch.nn.functional.cosine_similarity(ours, true, dim=1)


def _scale_free(
    m: EvalModel, w: Window, seq: torch.Tensor, gt: torch.Tensor, poses: torch.Tensor
) -> dict:
    """An SfmLearnerNet's depth of the last frame with the "P" scale (PoseNet's ``poses``:
    displacement between the window's first and last frames against the measured one) and the
    "GT" one; ``references``: the first frame for both."""
    n, _, h, wd = seq.shape
    raw = _full(m.net(torch.cat([seq[-1], seq[-1]])[None])[0].float(), h, wd)[None]
    first = torch.from_numpy(w.position[0]).float().to(seq.device)[None]  # metres from t
    p = pose_scale(poses, torch.tensor([[0, n - 1]], device=seq.device), first)
    g = metrics.median_scale(raw, gt[None]).to(raw.dtype)
    return {SCALE_P: raw[0] * p[0], SCALE_GT: raw[0] * g[0], "shifts": {},
            "references": {SCALE_P: 0, SCALE_GT: 0}}  # fmt: skip


def _depthnet(m: EvalModel, w: Window, seq: torch.Tensor, poses: torch.Tensor | None) -> dict:
    """DepthNet's depth of the last frame from the pair (r, t) whose mean output is closest to
    PAIR_TARGET_DEPTH (SCALE_P) and from the pair whose measured displacement is closest to d0
    (SCALE_P_FIXED), each reference stabilised first (:attr:`EvalModel.stabilise`; PoseNet's
    rotation from ``poses``), × ‖t_r‖/d0; ``references``: ``{scale: the pair's reference}``."""
    n, _, h, wd = seq.shape
    refs = torch.arange(n - 1, device=seq.device)
    pairs = torch.cat([seq[:-1], seq[-1:].expand(n - 1, -1, -1, -1)], 1)  # (N − 1, 6, H, W)
    if not (m.stabilise == STABILISE_KNOWN and w.stabilised):
        K = torch.from_numpy(w.K).float().to(seq.device)
        known = torch.from_numpy(w.rotation).float().to(seq.device).expand(n - 1, -1, -1, -1)
        tgt = torch.full((n - 1,), n - 1, device=seq.device)
        if m.stabilise == STABILISE_POSENET:
            mode, turns = "6dof", poses.expand(n - 1, -1, -1)
        else:
            mode, turns = "orientation", torch.zeros(n - 1, n, 3, device=seq.device)
        pairs = Stabiliser(mode, known, tgt, refs, K)(pairs, turns)
    raw = m.net(pairs)[0].float()  # (N − 1, 1, h, w), metres at d0
    if m.clamp is not None:
        raw = raw.clamp(*m.clamp)
    moved = np.linalg.norm(w.position[: n - 1], axis=1)  # metres from each reference to t
    chosen = {
        SCALE_P: choose_pair(raw.mean((1, 2, 3))),
        SCALE_P_FIXED: choose_pair(torch.from_numpy(moved), m.d0),
    }
    out: dict = {s: _full(raw[k : k + 1] * (moved[k] / m.d0), h, wd) for s, k in chosen.items()}
    out["shifts"] = {s: n - 1 - k for s, k in chosen.items()}
    out["references"] = chosen
    return out


@dataclass
class Tally:
    """Per-image metrics of one (model, scale, orientation), the shifts DepthNet used and the
    cosines of PoseNet's translation (one a sequence; none without PoseNet)."""

    per_image: dict[str, list[torch.Tensor]] = field(default_factory=dict)
    shifts: Counter = field(default_factory=Counter)
    cosines: list[float] = field(default_factory=list)

    def add(self, pred: torch.Tensor, gt: torch.Tensor) -> None:
        for k, v in metrics.image_metrics(pred[None], gt[None]).items():
            self.per_image.setdefault(k, []).append(v.cpu())

    def summary(self) -> dict:
        agg = metrics.aggregate({k: torch.cat(v) for k, v in self.per_image.items()})
        out = {k: agg[k] for k in metrics.METRICS}
        out["images"] = agg["images"]
        out["shifts_used"] = " ".join(f"{s}:{c}" for s, c in sorted(self.shifts.items()))
        return {**out, **self.pose_summary()}

    def pose_summary(self) -> dict:
        """:data:`POSE_COSINE` (the mean cosine) and :data:`POSE_COSINE_SHARE` (the share of
        cosines above :data:`POSE_COSINE_GOOD`), both None without cosines."""
        if not self.cosines:
            return {POSE_COSINE: None, POSE_COSINE_SHARE: None}
        c = np.asarray(self.cosines, np.float64)
        return {
            POSE_COSINE: float(c.mean()),
            POSE_COSINE_SHARE: float((c > POSE_COSINE_GOOD).mean()),
        }


def test_scenes(data: Path, split: str, limit: int | None) -> list[Scene]:
    """The split's scenes (first ``limit``); FieldError on ``data`` when there is none or one is
    shorter than a window, on ``limit`` when below 1."""
    if limit is not None and limit < 1:
        raise FieldError("limit", f"must be at least 1, got {limit}")
    scenes = read_scenes(data, split, limit)
    if not scenes:
        raise FieldError("data", f"no scene in the {split} split", where=f" {data}")
    short = [s for s in scenes if s.frames < SEQUENCE_LENGTH]
    if short:
        raise FieldError(
            "data", f"scene {short[0].index} has {short[0].frames} frames; sequences of "
            f"{SEQUENCE_LENGTH} are scored", where=f" {data}",
        )  # fmt: skip
    return scenes


def check_size(models: list[EvalModel], scenes: list[Scene], data: Path) -> None:
    """FieldError on ``data`` when a checkpoint was trained on another frame size, or its
    network cannot read the frames (eval's own check, runner.check_frame_size)."""
    from ..engine.runner import check_frame_size, frame_size

    size = frame_size(scenes)
    for m in models:
        check_frame_size({"camera": m.camera}, m.net, size, data, m.checkpoint)


def evaluate(
    models: list[EvalModel],
    scenes: list[Scene],
    device: torch.device,
    orientations: tuple[str, ...] = (UPRIGHT,),
    progress: bool = True,
) -> list[dict]:
    """One row per (orientation, model, scale): the model's fields, the metrics, ``images``,
    ``sequences``, ``shifts_used`` (frames between the chosen reference and t: count),
    :data:`POSE_COSINE` and :data:`POSE_COSINE_SHARE` (None without PoseNet)."""
    from tqdm import tqdm

    for m in models:
        if m.net is not None:
            m.net.to(device)
    tallies = {(o, i, s): Tally() for o in orientations for i, m in enumerate(models)
               for s in m.scales}  # fmt: skip
    count = 0
    for scene in tqdm(scenes, desc="sequences", unit="scene", disable=not progress):
        for window in scene_windows(scene):
            count += 1
            for o in orientations:
                w = upside_down(window) if o == UPSIDE_DOWN else window
                gt = torch.from_numpy(np.ascontiguousarray(w.depth)).to(device)
                for i, m in enumerate(models):
                    out = predict(m, w, device)
                    for s in m.scales:
                        tallies[o, i, s].add(out[s], gt)
                    for s, shift in out["shifts"].items():
                        tallies[o, i, s].shifts[shift] += 1
                    for s, cosine in out["pose_cosine"].items():
                        tallies[o, i, s].cosines.append(cosine)
    rows = []
    for (o, i, s), tally in tallies.items():
        m = models[i]
        rows.append({
            "orientation": o, "model": m.name, "checkpoint": m.checkpoint,
            "training_set": m.training_set, "scale": s, "pose": m.pose or "",
            "occlusion": m.occlusion, "stabilisation": m.stabilise, **tally.summary(),
            "sequences": count,
        })  # fmt: skip
    return rows
