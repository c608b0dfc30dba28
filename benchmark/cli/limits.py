"""The bounds of every numeric option of ``stillbox-bench``, in one table (:data:`LIMITS`), and
the click types that refuse a value beyond them while click parses the command line: before a
command reads or writes anything, in one line naming the flag (exit code 2), e.g. ``Invalid
value for '--threads': must be at most 1,024 threads, got 100,000``.

Numeric options declare ``type=INT`` or ``type=FLOAT`` (:class:`Bounded`: click's own, then
the row of the option's flag in the command being parsed); ``--res`` (N or WxH pixels)
declares :data:`RESOLUTION`, bounded per side; a comma-separated list declares ``type=INTS``
or ``type=FLOATS`` (:class:`Numbers`), each value bounded. A new numeric option needs one row
here: tests/test_cli_bounds.py walks every command's options and names one without a row.
Where a library constant already says how far a value may go, the row imports it; the
libraries keep their own checks of the lower bounds for callers of their Python API.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import click

from stillbox_gen.arguments import parse_resolution
from stillbox_gen.conventions import LIMITS as GENERATOR_LIMITS
from stillbox_gen.conventions import MAX_DEPTH
from stillbox_gen.errors import ConfigError

from ..core.config import MAX_SEED
from ..core.multishift import BETA_MAX, BETA_MIN, MAX_SHIFTS
from ..engine.footage_job import MAX_MAX_SHIFT, MAX_RES


@dataclass(frozen=True)
class Bound:
    """The values a numeric option takes: finite, from ``low`` to ``high`` in ``unit``;
    ``above``: ``low`` itself excluded (e.g. a positive number of metres), ``below``: ``high``
    excluded."""

    low: float
    high: float
    unit: str = ""
    above: bool = False
    below: bool = False

    def problem(self, value: float) -> str | None:
        """Why ``value`` is out of bounds ("must be at most 1,024 threads, got 100,000"), None
        when it is within them."""
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be a finite number, got {value}"
        too_low = value < self.low or (self.above and value == self.low)
        too_high = value > self.high or (self.below and value == self.high)
        if self.below and (too_low or too_high):  # an open interval: (0, 180) degrees
            interval = f"{'(' if self.above else '['}{_shown(self.low)}, {_shown(self.high)})"
            return f"must be in {f'{interval} {self.unit}'.rstrip()}, got {_shown(value)}"
        if too_low:
            side = "above" if self.above else "at least"
            return f"must be {side} {self._amount(self.low)}, got {_shown(value)}"
        if too_high:
            return f"must be at most {self._amount(self.high)}, got {_shown(value)}"
        return None

    def _amount(self, value: float) -> str:
        return f"{_shown(value)} {self.unit}".rstrip()


def _shown(value: float) -> str:
    """1,024 for an integer, 0.001 or 1e+300 for a float (never hundreds of digits)."""
    if isinstance(value, float) and not value.is_integer():
        return f"{value:g}"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) < 1e15 else f"{value:g}"
    return f"{value:,}"


# Shared magnitudes (why each is where it is):
THREADS = GENERATOR_LIMITS["threads"][0]  # more than any CPU has; 100,000 exhausts OpenMP
SCENES = GENERATOR_LIMITS["scenes"][0]  # the generator's largest dataset
CAMERA_SIDE = GENERATOR_LIMITS["camera.width"][0]  # the generator's largest frame
assert GENERATOR_LIMITS["camera.height"][0] == CAMERA_SIDE  # one bound per side of --res
FRAMES = GENERATOR_LIMITS["camera.frames"][0]  # the generator's longest scene
WORKERS = GENERATOR_LIMITS["workers"][0]  # processes of about 500 MB each
STEPS = 10**9  # optimiser steps: decades of training on this machine, still exact in float64
BATCH = 4096  # samples per step: 16 times the recipe's 256, about 1 GB of 64 px pairs
FLIGHT_STEPS = 100_000  # control steps of one episode, whose per-step record stays in memory

#: The bounds of every numeric option: by flag, or by "command flag" where a command's option of
#: that name means something else (its row is taken first). ``--res`` bounds each side.
LIMITS: dict[str, Bound] = {
    # training (run, compare, finetune) and its checkpoints and logs
    "--epochs": Bound(1, 100_000, "epochs"),  # the recipe: 55
    "--max-steps": Bound(1, STEPS, "steps"),
    "--epoch-size": Bound(0, STEPS, "steps"),  # 0: one pass over the training frames
    "--steps": Bound(1, STEPS, "steps"),
    "--pose-warmup": Bound(0, STEPS, "steps"),
    "--ckpt-every": Bound(0, STEPS, "steps"),  # 0: at epoch ends (run) or the end (finetune)
    "--log-every": Bound(1, STEPS, "steps"),
    "--batch-size": Bound(1, BATCH, "samples"),  # eval: pairs per forward pass
    # any finite rate: one that diverges stops the training in one line naming --lr (the
    # non-finite guard of engine.train, tested with --lr 1e300)
    "--lr": Bound(0.0, sys.float_info.max, above=True),
    "--pose-lr": Bound(0.0, sys.float_info.max, above=True),  # PoseNet's own, guarded the same
    "--smooth-weight": Bound(0.0, 1000.0),  # λ; the toy study's grid ends at 100
    "--shift": Bound(1, FRAMES - 1, "frames"),  # below the frames of a scene
    "--seed": Bound(0, MAX_SEED),  # torch.manual_seed takes an unsigned 64-bit integer
    "--threads": Bound(0, THREADS, "threads"),  # 0: torch's default
    "toy --threads": Bound(1, THREADS, "threads"),  # the kernels' own thread count
    "toy --jobs": Bound(1, WORKERS, "worker processes"),
    "toy --iterations": Bound(1, 1_000_000, "iterations"),  # the thesis: 10,000
    "toy --odm-every": Bound(1, 1_000_000, "iterations"),
    # the (λ, κ) grid, each value: the thesis' ends at 100 and 3
    "toy --lambdas": Bound(0.0, 1e6, above=True),
    "toy --kappas": Bound(0.0, 1e6, above=True),
    # scoring (eval, speed, eval-multishift, eval-sequences)
    "--displacement": Bound(0.0, MAX_DEPTH, "m", above=True),  # beyond any depth it scores
    "--scenes": Bound(1, SCENES, "scenes"),
    "--time-res": Bound(64, CAMERA_SIDE, "pixels"),  # multiples of 64: speed's own check
    "--warmup": Bound(0, 100_000, "passes"),
    "--repeats": Bound(1, 100_000, "passes"),
    # each value of the list; a GMAC column runs the network once at that size
    "speed --resolutions": Bound(64, CAMERA_SIDE, "pixels"),
    "speed --batches": Bound(1, BATCH, "samples"),
    # footage (infer, finetune): its motion and camera; infer's frame shifts and outputs
    # 1 mm/s to 1 km/s, 0.01 to 1000 frames/s: a frame's displacement (speed / fps) stays within
    # 1 µm..100 km, so the shift reaching the nominal displacement cannot overflow; the
    # preview's MPEG-4 time base takes at most 65,535 frames/s
    "--speed": Bound(0.001, 1000.0, "m/s"),
    "--fps": Bound(0.01, 1000.0, "frames/s"),
    "--fov": Bound(0.0, 180.0, "degrees", above=True, below=True),
    "--train-fov": Bound(0.0, 180.0, "degrees", above=True, below=True),
    "--focal": Bound(1.0, 1e6, "pixels"),  # 1e6 px: a 0.5 degree view of an 8K frame
    "--res": Bound(1, MAX_RES, "pixels"),  # the network's input (multiples of 64: infer's check)
    "--shifts": Bound(1, MAX_SHIFTS, "pairs per frame"),
    "--fixed-shift": Bound(1, MAX_MAX_SHIFT, "frames"),  # frames kept in memory
    "--max-shift": Bound(1, MAX_MAX_SHIFT, "frames"),
    "--ema": Bound(0.0, 1.0, below=True),  # λ of eq. 6.2
    "--beta-mean": Bound(BETA_MIN, BETA_MAX, above=True, below=True),
    "--max-depth": Bound(0.0, 100 * MAX_DEPTH, "m", above=True),  # the colour map's end
    # closed-loop flight (fly)
    "fly --episodes": Bound(1, SCENES, "episodes"),  # episode k flies scene k
    "fly --res": Bound(1, CAMERA_SIDE, "pixels"),  # the rendered camera, as the generator's
    "fly --max-steps": Bound(1, FLIGHT_STEPS, "control steps"),
    "fly --constant-depth": Bound(0.0, MAX_DEPTH, "m", above=True),
}


def bound_of(command: str, flag: str) -> Bound | None:
    """The row of LIMITS for ``flag`` of ``command`` (None when it has none)."""
    return LIMITS.get(f"{command} {flag}", LIMITS.get(flag))


def _flag(param: click.Parameter) -> str:
    """The option's long flag (``--threads``), as messages and LIMITS name it."""
    return max(param.opts, key=len)


def _command(ctx: click.Context | None) -> str:
    """The name of the command being parsed ("" outside one)."""
    if ctx is None or ctx.command is None:
        return ""
    return ctx.command.name or ""


class Bounded(click.ParamType):
    """click's INTEGER or FLOAT (``base``) within the bound LIMITS has for the option in the
    command being parsed: a value beyond it fails as click's own conversion errors do (exit
    code 2, one line naming the flag). Declared by the option (``type=INT``, ``type=FLOAT``); an
    option without a row is not bounded, and tests/test_cli_bounds.py names it."""

    def __init__(self, base: click.ParamType):
        self.base = base
        self.name = base.name  # --help shows INTEGER or FLOAT, as before

    def convert(self, value, param: click.Parameter | None, ctx: click.Context | None):
        number = self.base.convert(value, param, ctx)
        bound = bound_of(_command(ctx), _flag(param)) if param is not None else None
        problem = bound.problem(number) if bound is not None else None
        if problem:
            self.fail(problem, param, ctx)
        return number


#: the types of the numeric options of stillbox-bench (instead of click's int and float)
INT = Bounded(click.INT)
FLOAT = Bounded(click.FLOAT)


class Resolution(click.ParamType):
    """``--res``: ``N`` or ``WxH`` -> (width, height) pixels, each side within the bound of the
    command's ``--res`` (LIMITS)."""

    name = "resolution"

    def get_metavar(self, param: click.Parameter, ctx: click.Context | None = None) -> str:
        return "N|WxH"

    def convert(self, value, param: click.Parameter | None, ctx: click.Context | None):
        if isinstance(value, tuple):  # already converted
            return value
        flag = _flag(param) if param is not None else "--res"
        try:
            size = parse_resolution(str(value), flag)
        except ConfigError as e:  # its message names the flag, which click adds again
            self.fail(str(e).removeprefix(f"{flag}: "), param, ctx)
        bound = bound_of(_command(ctx), flag)
        for side in size if bound is not None else ():
            problem = bound.problem(side)
            if problem:
                self.fail(f"each side {problem}", param, ctx)
        return size


RESOLUTION = Resolution()


class Numbers(click.ParamType):
    """Comma-separated numbers (``8,256``) -> a tuple of click's INTEGER or FLOAT (``base``),
    each within the row of the option's flag in the command being parsed."""

    def __init__(self, base: click.ParamType):
        self.base = base
        self.name = f"{base.name} list"
        self.what = "integers" if isinstance(base, click.types.IntParamType) else "numbers"

    def get_metavar(self, param: click.Parameter, ctx: click.Context | None = None) -> str:
        return "N,N,..."

    def convert(self, value, param: click.Parameter | None, ctx: click.Context | None):
        if isinstance(value, tuple):  # already converted
            return value
        items = [v.strip() for v in str(value).split(",")]
        bound = bound_of(_command(ctx), _flag(param)) if param is not None else None
        numbers = []
        for item in items:
            try:
                number = int(item) if self.what == "integers" else float(item)
            except ValueError:
                self.fail(f"expected comma-separated {self.what}, got '{value}'", param, ctx)
            problem = bound.problem(number) if bound is not None else None
            if problem:
                self.fail(f"each value {problem}", param, ctx)
            numbers.append(number)
        return tuple(numbers)


#: the types of the options taking a list of numbers
INTS = Numbers(click.INT)
FLOATS = Numbers(click.FLOAT)
