"""Where code is defined: an error about a user's problem or method leads with its file and
line, whichever check finds it (compiler style, ``FILE:LINE: message``)."""

from __future__ import annotations

import inspect
from types import FrameType


def defined_at(obj) -> str:
    """``FILE:LINE`` where ``obj`` is defined (a function, a class) or stands (a frame, or
    the place itself as a ``FILE:LINE`` string); ``""`` where its source is not in a file (a
    built-in, code typed at a prompt)."""
    if isinstance(obj, str):
        return obj
    if isinstance(obj, FrameType):
        file, line = obj.f_code.co_filename, obj.f_lineno
    else:
        try:
            file, line = inspect.getsourcefile(obj), inspect.getsourcelines(obj)[1]
        except (TypeError, OSError):
            return ""
    return "" if not file or file.startswith("<") else f"{file}:{line}"


def located(message: str, *objects) -> str:
    """``message`` led by the ``FILE:LINE`` of the first of ``objects`` whose source is in a
    file (:func:`defined_at`), once: a message that names the place already (an error that
    a check located, wrapped by its caller) has it moved to the front. Unchanged where none
    of ``objects`` has a source file."""
    for obj in objects:
        where = defined_at(obj)
        if where:
            return f"{where}: {message.replace(f'{where}: ', '', 1)}"
    return message


def caller(*skip: str) -> FrameType | None:
    """The innermost frame on the stack outside the files ``skip`` and outside generated
    code (a dataclass's ``__init__``): where the user's call of a constructor stands, for
    :func:`located` (``None`` at the bottom of the stack)."""
    frame = inspect.currentframe().f_back
    while frame is not None and (frame.f_code.co_filename in (*skip, __file__)
                                 or frame.f_code.co_filename.startswith("<")):
        frame = frame.f_back
    return frame


class ArgumentError(ValueError):
    """An argument of a constructor of the problem-authoring API that is out of its
    contract, refused where the object is made: the message leads with the ``FILE:LINE``
    of the user's call (:func:`caller`)."""


def refuse(message: str, *skip: str) -> ArgumentError:
    """:class:`ArgumentError` with ``message`` led by the place of the call that reached
    the files ``skip`` (the constructor's own modules)."""
    return ArgumentError(located(message, caller(*skip)))
