"""Which exceptions are the user's to fix (one line, exit status 2) and which are bugs (a traceback).

A ``ValueError`` or ``RuntimeError`` in general means a bug: catching those broadly
would print a real defect as a one-line "user error" and hide where it happened. So
only dedicated types count as user errors: :class:`UserError` (raised by the command
line's own modules), the error type of each layer that checks user input (bags,
params files, weights files, plant formulas, field paths, recordings), and ``OSError``
(a path that does not exist or cannot be written, named in the message).
"""

from __future__ import annotations

import sys


class UserError(Exception):
    """A problem the user can fix: printed as one line, exit status 2."""


class MissingExtra(UserError):
    """An optional dependency (a setup.py extra) that the asked-for feature needs is not installed."""


def require_extra(module: str, extra: str, feature: str) -> None:
    """Raise :class:`MissingExtra` naming the pip extra when ``module`` cannot be imported.

    Plotting and progress bars are extras (most runs need neither, and matplotlib is the
    largest dependency); without this the user would get a ModuleNotFoundError traceback
    from deep inside a run instead of the one line that says what to install.
    """
    import importlib.util

    if importlib.util.find_spec(module) is None:
        raise MissingExtra(f"{feature} need {module}, which is not installed: pip install 'lenn_ros[{extra}]'")


#: (module, class) of each layer's own user-error type. Looked up only in modules already
#: imported: an exception of that type can only come from a module that is loaded, and the
#: command line need not import the bag reader (rosbags) just to know its error type.
LAYER_ERRORS = (
    ("lenn_ros.bag.errors", "BagError"),
    ("lenn_ros.config", "ConfigError"),
    ("lenn_ros.service", "RecordingError"),
    ("lenn_ros.fit.data", "FitError"),
    ("lenn_ros.table", "TableError"),
    ("lenn_ros.core.networks", "ModelFileError"),
    ("lenn_ros.paper.expression", "ExpressionError"),
    ("lenn_ros.core.fields", "FieldError"),
    ("lenn_ros.core.threads", "ThreadsError"),
)


def user_error_types() -> tuple[type[BaseException], ...]:
    """The exception types to report as one line: the dedicated ones, never plain ValueError."""
    types: list[type[BaseException]] = [UserError, OSError]
    for module_name, class_name in LAYER_ERRORS:
        module = sys.modules.get(module_name)
        error_type = getattr(module, class_name, None) if module is not None else None
        if isinstance(error_type, type) and issubclass(error_type, BaseException):
            types.append(error_type)
    return tuple(types)
