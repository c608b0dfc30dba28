"""Training DepthNet without depth (thesis §5.2, Fig. 5.1, eqs. 5.2-5.5): the training step.

Per sample (benchmark.unsupervised.sequences): N frames, a target t and a reference r. PoseNet
gives every frame's translation relative to the last frame; they are compensated to the target
(:func:`compensate`, the target's becomes 0) and normalised (:func:`normalise_translations`,
eq. 5.2) so that ``‖t_r‖ = d0``, the nominal displacement the supervised DepthNet answers for
(``shift`` × the training split's median metres per frame: Trainer's ``nominal_displacement``),
so the network keeps the supervised convention and is scored the same way. DepthNet reads the
(r, t) pair; every frame i ≠ t is warped to t with DepthNet's depth and the normalised
translations (benchmark.unsupervised.reprojection.inverse_warp), and the loss is eq. 5.5:

    L = Σ_s w_s · (L_p^s + λ·L_gdiff(ξ_s, I_t^s, κ)),   w_s = 1/2^s (the recipe's loss_weights)

with L_p^s (eq. 5.3, α = 0.15) the sum over references of the mean L1 + DSSIM error at full
resolution, from the scale-s depth upsampled bilinearly (§4.7.1), over the pixels the warp
keeps (and, with ``--occlusion``, not occluded); ξ_s = 1/θ_s and I_t area-downsampled to scale s
(eq. 5.4; scales smaller than 3×3 pixels have no interior Laplacian and no smooth term).
DepthNet's depth is floored at metrics.MIN_DEPTH (0.1 m) before use (:func:`floored`): its
1 + ELU output underflows to 0 in float32, where ξ would be infinite (the author's code adds
0.01 m instead). DepthPoseNet's DepthNet starts flat (core.posenet.INITIAL_DEPTH), not below it.
λ, κ: Table 4.1's gradient-diffusion optimum for the occlusion setting (κ 0.3; λ 30 without the
occlusion module, 0.3 with it), as §5.2.4 says, with λ times :data:`SMOOTH_SCALE` (unless the
recipe sets them): Table 4.1's λ weighs means over the toy study's 200-pixel maps of metric depth,
eq. 5.5's smooth term means over DepthNet's 16-to-1-pixel maps of mean-normalised inverse depth
(:func:`mean_normalised`; see SMOOTH_SCALE). The toy study keeps the thesis' raw ξ: its depth's
scale is fixed by the known motion and its losses are Table 4.1's.

Where this differs from the author's code (ClementPinard/unsupervised-depthnet,
``train_img_pairs.py``; the thesis is followed): the author weighs each scale's photometric
term by its size ratio and sums the smooth loss over scales unweighted, eq. 5.5 weighs both by
1/2^s; the author's ε is 1e-5 in training (none in validation), we use :data:`EPSILON` in both.
The occlusion mask is computed once per reference from the finest scale's (detached, upsampled)
depth and used at every scale (the thesis does not say; one direct warp instead of five).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..core.metrics import MIN_DEPTH
from ..core.posenet import EPSILON
from ..core.registry import Target
from ..engine.steps import training_step
from .reprojection import (
    SSIM_WEIGHT,
    gradient_diffusion_loss,
    inverse_warp,
    kornia_dssim_map,
    l1_map,
    masked_mean,
    occlusion_mask,
    photometric_map,
)
from .rotation import ROTATING_MODES, Stabiliser, target_rotations
from .toy import thesis_value

#: The smooth loss of §5.2.4 (Table 4.1's name)
SMOOTH_LOSS = "gradient_diffusion"
#: Table 4.1's λ is multiplied by this for eq. 5.5 (30 -> 0.003 without the occlusion module).
#: The smooth term is on mean-normalised ξ (:func:`mean_normalised`). On 64 scenes of a 64 px
#: StillBox (docs/results/finetune/smooth_scale.py: true depth through DepthNet's scales, frame 4)
#: the truth's smooth loss (Σ_s w_s·L_s) is 2.41; on 16 rendered samples its photometric loss was
#: 0.175 against 0.232 for each map's median depth (L_s = 0), so the truth has the lowest loss only
#: for λ < 0.024: with Table 4.1's λ = 30 a flat map wins and training flattens the depth. At
#: 0.003, λ·L_s is 4 % of the truth's photometric loss, the share the raw term had at λ = 0.3
#: (this scale was 0.01 before the normalisation; raw / normalised on the truth is 0.0095).
SMOOTH_SCALE = 1e-4
#: Elements (reference × channel × pixel) of the references whose photometric error is computed
#: at once: L1 + SSIM make about a dozen full-size intermediates, which then stay in the CPU's
#: cache instead of memory (4 MB each; 1.7× faster at 128 px, a 32 MB L3; same values)
PHOTOMETRIC_CHUNK = 2**20


def chunked_photometric_map(target: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
    """:func:`~.reprojection.photometric_map` (eq. 5.3, α = SSIM_WEIGHT) of ``G`` targets
    ``(G, 1, C, H, W)`` against their references ``(G, R, C, H, W)``: ``(G, R, 1, H, W)``,
    computed :data:`PHOTOMETRIC_CHUNK` elements at a time (the same values)."""
    per = max(1, PHOTOMETRIC_CHUNK // max(1, warped[0].numel()))
    return torch.cat([
        photometric_map(target[i : i + per], warped[i : i + per], SSIM_WEIGHT)
        for i in range(0, len(warped), per)
    ])  # fmt: skip


def mean_normalised(xi: torch.Tensor) -> torch.Tensor:
    """``ξ / mean(ξ)`` per sample over its ``(…, H, W)`` map: the smooth term of eq. 5.5 on it is
    unchanged when every depth is scaled by one factor. On ξ as it is, the term scales with ξ²,
    so pushing the whole map farther lowers it wherever the photometric term is weak (around the
    focus of expansion, far pixels): fine-tuning did that (docs/results/finetune/README.md). The
    convention of Godard et al.'s Monodepth2; the mean keeps its gradient."""
    return xi / xi.mean((-2, -1), keepdim=True)


def floored(depth: torch.Tensor) -> torch.Tensor:
    """``max(θ, MIN_DEPTH)`` in value, with θ's gradient everywhere (straight through), so that
    the pixels under the floor, where a DepthNet starts for a good share of them, are still
    pushed by the losses (a plain clamp would leave them without gradient)."""
    return depth + (depth.clamp(min=MIN_DEPTH) - depth).detach()


def compensate(
    poses: torch.Tensor, target_index: torch.Tensor, rotations: torch.Tensor | None = None
) -> torch.Tensor:
    """Translations relative to the last frame ``(B, N, 3)`` -> relative to the target frame:
    ``τ_i − τ_t`` (stabilised frames: ``X_i = X_t + τ_i − τ_t``); the target's row is 0. With
    ``rotations`` ``R_{t→i}`` ``(B, N, 3, 3)`` (rotating data, benchmark.unsupervised.rotation):
    ``τ_i − R_{t→i}·τ_t`` (``X_i = R_{t→i}·X_t + τ_i − R_{t→i}·τ_t``)."""
    rows = torch.arange(poses.shape[0], device=poses.device)
    if rotations is None:
        return poses - poses[rows, target_index].unsqueeze(1)
    return poses - (rotations @ poses[rows, target_index].view(-1, 1, 3, 1)).squeeze(-1)


def true_translations(batch: dict) -> torch.Tensor:
    """``(B, N, 3)`` metres: each frame's true ``τ_i`` (``X_i = R_{t→i}·X_t + τ_i``, the warps'
    convention) from a batch's camera positions ``translation`` ``p_i`` (target axes) and its
    ``rotation`` ``R_{t→i}`` when it has one: ``τ_i = −R_{t→i}·p_i`` (``−p_i`` on stabilised
    data)."""
    p = batch["translation"].float()
    rotation = batch.get("rotation")
    if rotation is None:
        return -p
    return -(rotation.float() @ p.unsqueeze(-1)).squeeze(-1)


def pose_cosine(batch: dict, translations: torch.Tensor) -> float:
    """Mean over a batch of the cosine between the translation used for each sample's reference
    (``translations`` ``(B, N, 3)``: PhotometricStep's, PoseNet's after compensation and eq. 5.2)
    and the true one (:func:`true_translations`): PoseNet's direction of motion, 1 when right."""
    rows = torch.arange(len(translations))
    ref = batch["reference_index"]
    known = true_translations(batch)[rows, ref].to(translations.device)
    cos = F.cosine_similarity(translations[rows, ref].detach().float(), known, dim=1)
    return float(cos.mean())


def normalise_translations(
    translations: torch.Tensor,
    reference_index: torch.Tensor,
    d0: float,
    eps: float = EPSILON,
) -> torch.Tensor:
    """Eq. 5.2: every translation ``(B, N, 3)`` times ``d0 / (ε + ‖t_r‖)``, ``t_r`` the
    reference's (one ratio per sample): ``‖t_r‖`` becomes ``d0`` (metres) up to ε."""
    rows = torch.arange(translations.shape[0], device=translations.device)
    norm = translations[rows, reference_index].norm(dim=1)
    return translations * (d0 / (eps + norm)).view(-1, 1, 1)


def smooth_settings(
    weight: float | None, kappa: float | None, occlusion: bool
) -> tuple[float, float]:
    """(λ, κ) of the smooth loss: the given values, else Table 4.1's gradient-diffusion optimum
    with the occlusion module off / on (§5.2.4), λ times :data:`SMOOTH_SCALE`."""
    table = thesis_value(SMOOTH_LOSS, occlusion, "lambda")
    lam = table * SMOOTH_SCALE if weight is None else weight
    kap = thesis_value(SMOOTH_LOSS, occlusion, "kappa") if kappa is None else kappa
    return float(lam), float(kap)


def reference_indices(target_index: torch.Tensor, frames: int) -> torch.Tensor:
    """``(B, N − 1)``: every frame index but the target's, in order."""
    every = torch.arange(frames, device=target_index.device).expand(len(target_index), frames)
    return every[every != target_index.unsqueeze(1)].view(-1, frames - 1)


class PhotometricStep:
    """One optimiser step of eq. 5.5 on a SequenceDataset batch; returns the loss (0-d).

    ``net``: the DepthPoseNet as trained (maybe compiled or DDP-wrapped; called with the pair
    and the sequence it returns both networks' outputs, see core.posenet.DepthPoseNet);
    ``weights``: w_s finest first;
    ``d0``: metres (None: no eq. 5.2, PoseNet's translations used as they are, SFMLearner's
    arbitrary scale); ``occlusion``: the occlusion module on; ``pose``: TrainConfig.pose
    (where the rotations come from, benchmark.unsupervised.rotation); ``known_translation``: the
    batch's known camera motion (``translation``, e.g. a drone's GPS) replaces PoseNet's
    translations in the warps (stabilised data; ``finetune --known-motion``); ``levers`` off:
    the photometric terms as first written, for benchmark.unsupervised.step_speed's baseline
    (each target repeated for its warps, kornia's SSIM; the same losses to float rounding).
    :meth:`losses` gives the terms.
    """

    def __init__(
        self,
        net: torch.nn.Module,
        opt: torch.optim.Optimizer,
        device: torch.device,
        weights,
        d0: float | None,
        smooth_weight: float,
        kappa: float,
        occlusion: bool = False,
        autocast: torch.dtype | None = None,
        pose: str = "translation",
        known_translation: bool = False,
        levers: bool = True,
    ):
        if known_translation and pose != "translation":
            raise ValueError("known_translation is for stabilised data (pose 'translation')")
        self.net, self.opt, self.device = net, opt, device
        self.weights, self.d0 = tuple(weights), d0
        self.smooth_weight, self.kappa, self.occlusion = smooth_weight, kappa, occlusion
        self.autocast, self.pose = autocast, pose
        self.known_translation, self.levers = known_translation, levers

    def _forward(self, batch: dict) -> tuple[list[torch.Tensor], torch.Tensor]:
        pair = batch["input"].to(self.device)
        sequence = batch["sequence"].to(self.device)
        args = (pair, sequence)
        if self.pose in ROTATING_MODES:  # DepthNet reads the stabilised pair (eq. 5.1)
            keys = ("rotation", "target_index", "reference_index", "K")
            args += (Stabiliser(self.pose, *(batch[k].to(self.device) for k in keys)),)
        if self.autocast is None:
            return self.net(*args)
        with torch.autocast(self.device.type, self.autocast):
            return self.net(*args)

    def losses(self, batch: dict) -> dict[str, torch.Tensor]:
        """``loss`` (eq. 5.5), ``photometric`` and ``smooth`` (their weighted sums over scales)
        and ``translations`` ``(B, N, 3)``: the translations used (metres once normalised)."""
        frames = batch["frames"].to(self.device)
        K = batch["K"].to(self.device)
        tgt = batch["target_index"].to(self.device)
        ref = batch["reference_index"].to(self.device)
        depths, poses = self._forward(batch)
        depths, poses = [floored(d.float()) for d in depths], poses.float()
        b, n, _, h, w = frames.shape
        rows = torch.arange(b, device=self.device)
        known = batch["rotation"].to(self.device) if self.pose in ROTATING_MODES else None
        rotations = target_rotations(self.pose, poses, known, tgt)  # R_{t→i}, None: identity
        translations = compensate(poses[..., :3], tgt, rotations)
        if self.known_translation:  # the batch's camera motion, X_i = X_t − T_i, not PoseNet's
            translations = -batch["translation"].to(self.device).float()
        if self.d0 is not None:
            translations = normalise_translations(translations, ref, self.d0)
        others = reference_indices(tgt, n)  # (B, N - 1)
        target = frames[rows, tgt]
        # every (scale, sample, reference) warped in one batch, scale-major then sample-major
        scales, pairs = len(depths), b * (n - 1)
        up = torch.cat(
            [F.interpolate(d, size=(h, w), mode="bilinear", align_corners=False) for d in depths]
        )  # (S·B, 1, H, W)
        up = up.view(scales, b, 1, h, w).repeat_interleave(n - 1, 1).reshape(-1, 1, h, w)
        picked = (rows.unsqueeze(1), others)
        refs = frames[picked].reshape(pairs, 3, h, w).repeat(scales, 1, 1, 1)
        moves = translations[picked].reshape(pairs, 3).repeat(scales, 1)
        Ks = K.repeat_interleave(n - 1, 0).repeat(scales, 1, 1)
        turns = None if rotations is None else rotations[picked].reshape(pairs, 3, 3)
        repeated = None if turns is None else turns.repeat(scales, 1, 1)
        warped, valid = inverse_warp(refs, up, repeated, moves, Ks)
        occluded = self._occlusions(depths[0], translations, others, K, (h, w), turns)
        if occluded is not None:
            valid = valid & ~occluded.repeat(scales, 1, 1, 1)
        if self.levers:  # one target for its N − 1 references, in chunks
            groups = target.repeat(scales, 1, 1, 1)[:, None]  # (S·B, 1, 3, H, W)
            error_map = chunked_photometric_map(groups, warped.view(scales * b, n - 1, 3, h, w))
            error_map = error_map.reshape(-1, 1, h, w)
        else:  # the target repeated for every warp, kornia's SSIM (step_speed's baseline)
            targets = target.repeat_interleave(n - 1, 0).repeat(scales, 1, 1, 1)
            l1 = l1_map(targets, warped)
            error_map = (1 - SSIM_WEIGHT) * l1 + SSIM_WEIGHT * kornia_dssim_map(targets, warped)
        errors = masked_mean(error_map, valid)
        per_scale = errors.view(scales, b, n - 1).sum(2).mean(1)  # eq. 5.3 per scale
        weights = torch.tensor(self.weights, dtype=per_scale.dtype, device=self.device)
        photo = (weights * per_scale).sum()
        smooth = frames.new_zeros(())
        for weight, depth in zip(self.weights, depths, strict=True):
            if min(depth.shape[-2:]) >= 3:
                image = F.adaptive_avg_pool2d(target, depth.shape[-2:])
                xi = mean_normalised(1 / depth)
                gdiff = gradient_diffusion_loss(xi, image, self.kappa).mean()
                smooth = smooth + weight * self.smooth_weight * gdiff
        return {"loss": photo + smooth, "photometric": photo, "smooth": smooth,
                "translations": translations}  # fmt: skip

    def _occlusions(self, depth, translations, others, K, size, turns=None) -> torch.Tensor | None:
        """``(B·(N − 1), 1, H, W)``, sample-major: the target pixels the occlusion module finds
        hidden in each reference (finest scale's depth, detached; ``turns``: the rotations
        ``(B·(N − 1), 3, 3)``, None for none), or None when it is off."""
        if not self.occlusion:
            return None
        b, refs = others.shape
        up = F.interpolate(depth.detach(), size=size, mode="bilinear", align_corners=False)
        moves = translations[torch.arange(b, device=depth.device).unsqueeze(1), others]
        return occlusion_mask(
            up.repeat_interleave(refs, 0),
            None if turns is None else turns.detach(),
            moves.reshape(-1, 3).detach(),
            K.repeat_interleave(refs, 0),
        )

    def update(self, batch: dict) -> dict[str, torch.Tensor]:
        """One optimiser step; returns :meth:`losses`' terms (before the step)."""
        terms = self.losses(batch)
        self.opt.zero_grad(set_to_none=True)
        terms["loss"].backward()
        self.opt.step()
        return terms

    def __call__(self, batch: dict) -> torch.Tensor:
        terms = self.update(batch)
        self._last = batch, {k: v.detach() for k, v in terms.items()}
        return terms["loss"]

    def logged(self) -> dict[str, float]:
        """steps.csv's columns of the last call beside its loss (benchmark.engine.steps): the
        ``photometric`` and ``smooth`` terms of eq. 5.5 and PoseNet's direction,
        ``pose_cosine`` (:func:`pose_cosine`; 1 with the known motion)."""
        batch, terms = self._last
        return {
            "photometric": float(terms["photometric"]),
            "smooth": float(terms["smooth"]),
            "pose_cosine": pose_cosine(batch, terms["translations"]),
        }


class PoseWarmup:
    """``run --pose-warmup``: a PhotometricStep whose DepthNet is frozen while
    ``progress["global_step"]`` (steps done, resumed ones included) is below ``steps``: no
    gradient and its BatchNorm's running statistics kept (eval mode), so PoseNet alone learns
    against a pretrained depth; from then on both learn, as without the warm-up."""

    def __init__(self, step: PhotometricStep, depth: torch.nn.Module, steps: int, progress: dict):
        self.step, self.depth, self.steps, self.progress = step, depth, steps, progress

    def __getattr__(self, name: str):  # the PhotometricStep's settings (d0, pose, ...)
        return getattr(self.step, name)

    def __call__(self, batch: dict) -> torch.Tensor:
        frozen = self.progress["global_step"] < self.steps
        self.depth.requires_grad_(not frozen)
        self.depth.train(not frozen)
        return self.step(batch)


@training_step(Target.VIDEO)
def video_training(cfg, net, opt, device, store, d0: float, autocast=None, progress=None):
    """The training set and step of a method learning from video (Target.VIDEO, registered in
    benchmark.engine.steps: ``depthnet-unsup*``, ``sfmlearner*``; Trainer.setup): a
    SequenceDataset of ``cfg.sequence_length`` frames over ``store`` and a PhotometricStep
    with ``d0`` metres, or without pose normalisation for a method whose depth has no scale
    (Scoring.SCALE_FREE: sfmlearner). FieldError on ``data`` when its scenes are shorter than a
    sequence, on ``shift`` when such a method's pairs do not fit in one (its "P" scale), on
    ``pose`` when the mode does not fit the network or the data (rotation.check_pose), on
    ``pose_warmup`` with ``known_motion`` (no PoseNet to warm up) or under DDP. With
    ``cfg.pose_warmup`` steps, the step is a :class:`PoseWarmup` reading ``progress``."""
    from ..core import registry
    from ..core.errors import FieldError, Ref
    from .rotation import check_pose
    from .sequences import SequenceDataset

    check_pose(cfg.pose, registry.MODELS[cfg.model].recipe.pose, store.scenes, cfg.data)
    frames = min(len(s.rgb) for s in store.scenes)
    if frames < cfg.sequence_length:
        raise FieldError(
            "data",
            f"scenes of {frames} frames; '{cfg.model}' trains on sequences of "
            f"{cfg.sequence_length}",
            where=f" {cfg.data}",
        )
    if registry.MODELS[cfg.model].kind.scored_as is registry.Scoring.SCALE_FREE:
        d0 = None
        if cfg.shift >= cfg.sequence_length:
            raise FieldError(
                "shift", f"'{cfg.model}' is scaled by PoseNet over sequences of "
                f"{cfg.sequence_length} frames: pairs closer than that, got {cfg.shift}",
            )  # fmt: skip
    if cfg.known_motion and (d0 is None or cfg.pose != "translation"):
        raise FieldError(
            "known_motion", f"is for stabilised data (--pose translation) and a method scaled "
            f"by the displacement (depthnet-unsup); got '{cfg.model}' with --pose {cfg.pose}",
        )  # fmt: skip
    lam, kappa = smooth_settings(cfg.smooth_weight, cfg.smooth_kappa, bool(cfg.occlusion))
    step = PhotometricStep(
        net, opt, device, cfg.loss_weights, d0, lam, kappa, bool(cfg.occlusion), autocast,
        cfg.pose, known_translation=bool(cfg.known_motion),
    )  # fmt: skip
    if cfg.pose_warmup:
        if cfg.known_motion:
            raise FieldError(
                "pose_warmup", "has no PoseNet to warm up with ", Ref("known_motion"),
                " (the dataset's translations replace PoseNet's)",
            )  # fmt: skip
        if isinstance(net, torch.nn.parallel.DistributedDataParallel):
            raise FieldError("pose_warmup", "is for one process (a frozen DepthNet under DDP)")
        inner = getattr(net, "_orig_mod", net)  # torch.compile's wrapper
        step = PoseWarmup(step, inner.depth, cfg.pose_warmup, progress)
    return SequenceDataset(store, cfg.sequence_length, cfg.seed), step
