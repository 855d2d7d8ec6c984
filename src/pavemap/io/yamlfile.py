"""Reading a YAML file a user gives (config, policy, manifest, class map, dataset): one error line per problem."""

from __future__ import annotations

import os
from pathlib import Path

from pavemap.errors import PavemapError


def read_yaml(path: str | os.PathLike, what: str) -> object:
    """The parsed content of the YAML file ``path`` (``what`` names it in errors, e.g. "manifest").

    PavemapError naming the file for a missing or unreadable file, text that is not UTF-8, invalid YAML, or
    YAML nested too deeply for the parser; never a traceback."""
    import yaml

    p = Path(path)
    try:
        return yaml.safe_load(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PavemapError(f"{p}: {what} not found") from None
    except UnicodeDecodeError as e:
        raise PavemapError(f"{p}: is not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start})") from None
    except OSError as e:
        raise PavemapError(f"{p}: cannot read the {what} ({e})") from None
    except yaml.YAMLError as e:
        raise PavemapError(f"{p}: invalid YAML ({' '.join(str(e).split())})") from None
    except RecursionError:
        raise PavemapError(f"{p}: YAML nested too deeply") from None


__all__ = ["read_yaml"]
