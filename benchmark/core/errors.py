"""Errors of the library in terms of its own fields; the command line words them with its flags.

A :class:`FieldError` names the field (of InferOptions, TrainConfig, or a function's parameter)
whose value is wrong, and may refer to other fields (:class:`Ref`). ``str(e)`` names them as
fields (``speed: give either speed M/S or poses CSV``); the command line renders the same
error with its flags (:meth:`FieldError.worded`: ``--speed: give either --speed M/S or ...``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Ref:
    """A reference to the field ``name`` inside an error's text."""

    name: str


class FieldError(ValueError):
    """A one-line error about the value of ``field``: ``<field><where>: <parts>``.

    ``where``: text right after the field's name (e.g. ``" runs/a/best.pt"``, the file it
    names); ``parts``: the message, strings and :class:`Ref` to other fields.
    """

    def __init__(self, field: str, *parts: str | Ref, where: str = "") -> None:
        self.field, self.parts, self.where = field, parts, where
        super().__init__(self.worded(str))

    def worded(self, name: Callable[[str], str]) -> str:
        """The message with every field named by ``name(field)`` (e.g. its flag)."""
        text = "".join(name(p.name) if isinstance(p, Ref) else p for p in self.parts)
        return f"{name(self.field)}{self.where}: {text}"
