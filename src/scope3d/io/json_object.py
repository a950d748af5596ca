"""Reading a JSON object from a file that may be anyone's: every failure is one InputError line."""
from __future__ import annotations

import json
import os

from scope3d.errors import InputError


def read_json_object(path: str | os.PathLike) -> dict:
    """The JSON object (``{...}``) in the file at ``path``. Any problem (not UTF-8, not JSON, an integer of
    thousands of digits, nesting deep enough to exhaust the parser's recursion, not an object) is one
    InputError line naming the file."""
    try:
        with open(path, encoding="utf-8") as handle:
            data = json.loads(handle.read())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except (UnicodeDecodeError, OSError) as exc:
        raise InputError(f"{path}: cannot read ({exc})") from None
    except ValueError as exc:  # an integer of more than 4300 digits
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:
        raise InputError(f"{path}: not valid JSON (arrays or objects nested too deeply)") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object {{...}}, found {type(data).__name__}")
    return data
