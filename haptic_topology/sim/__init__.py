"""Offline lock-step simulation of the haptic loop, scenarios, traces and plots.

The names below are imported when first used (PEP 562): a process that only reads traces
or bags (``analyze``, ``run``'s analysis) does not load the simulation's compiled code.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {'simulate': 'lockstep', 'Scenario': 'scenario', 'load_scenario': 'scenario',
            'Trace': 'trace', 'format_summary': 'trace', 'VirtualEnvironment': 've'}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    return getattr(importlib.import_module(f'{__name__}.{_EXPORTS[name]}'), name)
