"""The one error type for bad configuration: a scenario file, a gain, a node parameter."""
from __future__ import annotations


class ScenarioError(ValueError):
    """Invalid configuration. The message names the file or parameter, the field and the fix."""
