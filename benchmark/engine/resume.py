"""What a resumed training keeps from its checkpoint: the training state it must hold and the
settings (TrainConfig fields) it may not change."""

from __future__ import annotations

from ..core.config import TrainConfig, flag_of
from ..core.errors import FieldError, Ref

RESUME_KEYS = ("optimizer", "scheduler", "state")
#: TrainConfig fields a resumed run keeps from its checkpoint's config (those without a flag are
#: set by the recipe only). A change would not be applied (optimiser, scheduler and sampling
#: position come from the checkpoint) or would make the run differ from the one config.json
#: describes, so it is refused; --max-steps, --device, --threads and the logging and speed
#: options may change (they are applied and recorded).
RESUMED_FIELDS = (
    *("epochs", "epoch_size", "batch_size", "lr", "shift", "depth_range", "seed", "pretrained"),
    *("optimizer", "momentum", "dampening", "beta2", "weight_decay"),
    *("milestones", "gamma", "loss_weights", "loss_scale"),
    *("sequence_length", "occlusion", "smooth_weight", "smooth_kappa", "pose"),
    *("known_motion", "pose_warmup", "pose_lr"),
)


def _plain(value):
    """A config value comparable across checkpoints (lists and tuples alike)."""
    return tuple(value) if isinstance(value, (list, tuple)) else value


def resumed_settings(ck: dict) -> dict:
    """The RESUMED_FIELDS of a checkpoint's recorded config (those it has)."""
    config = ck.get("config") if isinstance(ck.get("config"), dict) else {}
    return {k: _plain(config[k]) for k in RESUMED_FIELDS if k in config}


def check_resumed_settings(cfg: TrainConfig, ck: dict, where: str) -> None:
    """ValueError naming the flag when ``cfg`` changes a setting the checkpoint ``ck`` (file
    ``where``) was trained with (RESUMED_FIELDS). More ``epochs`` are allowed when the recipe has
    no milestones (its learning rate does not depend on the epoch count): the run continues past
    its planned end as if it had been started with them."""
    for field, then in resumed_settings(ck).items():
        now = _plain(getattr(cfg, field))
        if now == then:
            continue
        if field == "epochs" and not cfg.milestones and now > then:
            continue
        if flag_of(field) is None:
            raise FieldError(
                "resume",
                f"trained with {field} {then}, this version's recipe has {now}",
                where=f" {where}",
            )
        shown = [
            ",".join(f"{v:g}" for v in x) if field == "depth_range" else x for x in (then, now)
        ]
        raise FieldError(
            field,
            f"the run was trained with {shown[0]}, not {shown[1]}; a resumed run keeps its "
            "settings (leave ", Ref(field), " out, or start a new ", Ref("out"), ")",
        )  # fmt: skip
