"""The exceptions torchsfm raises. Every message names the argument and the problem.

All of them derive from :class:`TorchSfmError`; the input errors are also ``ValueError`` so that
callers that already catch ``ValueError`` keep working. The command line turns any of them into
one line on stderr and a non-zero exit.
"""


class TorchSfmError(Exception):
    """Base class of every error torchsfm raises on purpose."""


class InputError(TorchSfmError, ValueError):
    """An argument is malformed: NaN/inf values, a wrong dtype, a bad option."""


class ShapeError(InputError):
    """A tensor has the wrong number of dimensions or a size that disagrees with another one."""


class NotEnoughDataError(InputError):
    """Fewer points, views or inliers than the method needs."""


class DegenerateConfigurationError(TorchSfmError, ValueError):
    """The data admit no unique answer: identical points, a singular K, no baseline, ..."""


class ConfigError(TorchSfmError, ValueError):
    """A configuration key is unknown or its value is out of range."""
