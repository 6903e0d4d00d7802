"""The one error hierarchy of vlm_vpr_ros.

Every error the package raises on bad input derives from :class:`VlmVprError`, so callers (the
node, the CLIs) can catch one type, log a clear message and keep running.
"""

from __future__ import annotations


class VlmVprError(Exception):
    """Base class of every error raised by vlm_vpr_ros on bad input or configuration."""


class ConfigError(VlmVprError, ValueError):
    """Unknown preset/provider name, unknown config key or an invalid value."""


class MapError(VlmVprError):
    """A map folder is missing, corrupt, of another version or does not match the descriptor."""


class DescriptorError(VlmVprError):
    """A descriptor cannot be created, fitted, loaded or applied (e.g. missing weights)."""


class ImageDecodeError(VlmVprError):
    """An image (file or message) cannot be decoded into pixels."""


class PriorError(VlmVprError):
    """A prior provider is misconfigured (runtime failures are PriorResult values, not raises)."""


class DataError(VlmVprError):
    """An input table (CSV of coordinates, priors, answers) is missing columns or malformed."""


class BagError(VlmVprError):
    """A bag is missing, truncated, corrupt or lacks the expected topics/types."""


class OutputError(VlmVprError, OSError):
    """An output cannot be written safely (unsafe target, disk full, no permission).

    Also an :class:`OSError`, so code that already treats write failures as OS errors keeps
    working."""
