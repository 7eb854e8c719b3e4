"""Checks on a learner's hyper-parameter overrides (``drape train --config``), before any stage runs.

Each override must have its default's type: a whole number where the default is an ``int``
(2.0 is taken as 2), a finite number where it is a ``float`` (an integer is accepted; text that
reads as the number, such as YAML's ``1e-3``, is taken as it), ``true``/``false`` for a ``bool``,
text for a ``str`` and a list for a list; ``None`` defaults take anything. Numbers are >= 0
(sizes, counts, rates and weights), except the keys in ``SIGNED``; ``lr`` and ``*_lr`` are > 0,
``batch_size`` >= 1 and ``dropout`` in [0, 1). A learner checks its own choices (kinds,
schedules, norms) after this.
"""
from __future__ import annotations

import math
from typing import Any

#: Keys whose numbers may be negative (a cosine threshold).
SIGNED = frozenset({"inner_leg_cosine"})


def checked_override(name: str, value: Any, default: Any) -> Any:
    """``value`` for the hyper-parameter ``name`` ('stage.key', used in the message) whose default is
    ``default``; raises ValueError naming it, the value and what was expected."""
    key = name.rsplit(".", 1)[-1]
    if default is None:
        return value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be true or false (got {value!r})")
        return value
    if isinstance(default, (int, float)):
        whole = isinstance(default, int)
        if isinstance(value, str):  # YAML reads 1e-3 (no dot) as text
            try:
                value = int(value) if whole else float(value)
            except ValueError:
                pass
        if whole and isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int if whole else (int, float)) or not math.isfinite(value):
            raise ValueError(f"{name} must be {'an integer' if whole else 'a finite number'} (got {value!r})")
        if (key == "lr" or key.endswith("_lr")) and not value > 0:
            raise ValueError(f"{name} must be > 0 (got {value!r})")
        if key == "batch_size" and value < 1:
            raise ValueError(f"{name} must be >= 1 (got {value!r})")
        if key == "dropout" and not 0 <= value < 1:
            raise ValueError(f"{name} must be in [0, 1) (got {value!r})")
        if key not in SIGNED and value < 0:
            raise ValueError(f"{name} must be >= 0 (got {value!r})")
        return value
    if isinstance(default, str) and not isinstance(value, str):
        raise ValueError(f"{name} must be text (got {value!r})")
    if isinstance(default, (list, tuple)) and not isinstance(value, (list, tuple)):
        raise ValueError(f"{name} must be a list (got {value!r})")
    return value
