"""The network folder's status file, ``NETWORK/network.json``: its name, its format and its reader.

Written by :mod:`pavemap.network.batch`; read by the batch itself, the register and the network page.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from pavemap.errors import PavemapError

NETWORK_FILE = "network.json"
FORMAT = "pavemap-network/1"


def read_network(net: str | os.PathLike) -> dict:
    """``NETWORK/network.json``; PavemapError when ``net`` is not a network folder."""
    p = Path(net) / NETWORK_FILE
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PavemapError(f"{net}: no {NETWORK_FILE} (is it a folder `pavemap batch` wrote?)") from None
    except (OSError, ValueError) as e:
        raise PavemapError(f"{p}: cannot read ({e})") from None
    if not isinstance(d, dict) or d.get("format") != FORMAT or not isinstance(d.get("drives"), list):
        raise PavemapError(f"{p}: not a pavemap network status file ({FORMAT})")
    return d


__all__ = ["FORMAT", "NETWORK_FILE", "read_network"]
