"""The estimators and their registry, keyed by the scenario's ``method:``. Adding a method is one
module here and one line in :data:`_BUILT_IN`; one outside the package is named by its import
path, ``method: my_module:MyMethod``, and :func:`get` imports it.
"""
from __future__ import annotations

import importlib
from typing import Any

from ..core.errors import ScenarioError
from .base import Estimator
from .boughellaba_tayebi import BoughellabaTayebi
from .de_carli import DeCarli
from .presenza import Presenza
from .tran_anderson_ahn import TranAndersonAhn

_BUILT_IN: tuple[type[Estimator], ...] = (BoughellabaTayebi, TranAndersonAhn, DeCarli,
                                        Presenza)
_REGISTRY: dict[str, type[Estimator]] = {}
# The method of a scenario that names none, and of an estimator node without a scenario file.
DEFAULT_METHOD = BoughellabaTayebi.method


def register(cls: type[Estimator]) -> type[Estimator]:
    """Make ``cls`` selectable as ``method: <cls.method>`` (usable as a class decorator)."""
    if cls.method in _REGISTRY and _REGISTRY[cls.method] is not cls:
        raise ValueError(f'method {cls.method!r} is already registered')
    _REGISTRY[cls.method] = cls
    return cls


def unregister(method: str) -> None:
    """Remove a registered method (built-in ones stay)."""
    if method in {c.method for c in _BUILT_IN}:
        raise ValueError(f'{method!r} is built in')
    _REGISTRY.pop(method, None)


def methods() -> tuple[str, ...]:
    """Every registered method, built-in ones first."""
    return tuple(_REGISTRY)


def get(method: str) -> type[Estimator]:
    """The class registered as ``method``, or imported and registered from its ``module:Class``
    path; ScenarioError naming the known ones if unknown."""
    if method in _REGISTRY:
        return _REGISTRY[method]
    if ':' not in method:
        raise ScenarioError(f'unknown method {method!r}. Fix: use one of: '
                            f'{", ".join(_REGISTRY)}, or a method\'s import path '
                            '(module:Class)')
    module, _, name = method.partition(':')
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise ScenarioError(f'method {method!r}: cannot import it ({exc}). Fix: put {module} on '
                            'the Python path (PYTHONPATH) of every process, or use one of: '
                            f'{", ".join(_REGISTRY)}') from None
    if not (isinstance(cls, type) and issubclass(cls, Estimator)):
        raise ScenarioError(f'method {method!r}: {name} is not an Estimator subclass. Fix: '
                            'name the class of the method')
    _REGISTRY[method] = cls
    return cls


def build(method: str, gains: Any) -> Estimator:
    """An instance of ``method`` with ``gains`` (its own ``Gains`` dataclass)."""
    cls = get(method)
    if not isinstance(gains, cls.Gains):
        raise TypeError(f'{method} takes {cls.Gains.__qualname__}, got {type(gains).__name__}')
    return cls(gains)


for _cls in _BUILT_IN:
    register(_cls)
