"""Credentials never leave the process: every URI lbo writes or prints has its password as ***.

Stores take their credentials best from the environment (``PGPASSWORD`` or ``~/.pgpass`` for
PostgreSQL, ``MLFLOW_TRACKING_USERNAME``/``MLFLOW_TRACKING_PASSWORD`` for an MLflow server), so
that no config holds them. A password written into a URI anyway (``postgresql://u:pw@host/db``,
``http://u:pw@host``) is replaced by ``***`` in MLflow params, tags and artifacts, in Hydra's
``.hydra/*.yaml`` files and in every printed line.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

MASK = "***"

# scheme://user:password@host. The password runs to the LAST @ of the URI before the host: a
# generated password may hold / : and even a raw @, which SQLAlchemy, psycopg and requests
# accept unencoded, so the secret is everything from the user's ':' to that @ (a URI is one
# token: it ends at white space or a quote). A URI whose path holds an @ (rare) is masked
# from its port on: more than needed, never less.
_USERINFO = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.\-]*://[^:/@\s'\"]*:)"
                       r"(?P<secret>[^\s'\"]*)(?P<at>@)(?=[^@\s'\"]*(?:[\s'\"]|$))")


# ?password=...&  (libpq and SQLAlchemy also take the password as a query parameter)
_QUERY = re.compile(r"(?P<key>[?&](?:password|passwd|sslpassword)=)[^&\s'\"#]*",
                    re.IGNORECASE)


def scrub(text: str) -> str:
    """``text`` with the password of every ``scheme://user:password@host``, and every
    ``?password=`` query value, replaced by ***."""
    text = _USERINFO.sub(lambda m: m["head"] + MASK + m["at"], text)
    return _QUERY.sub(lambda m: m["key"] + MASK, text)


def scrub_tree(node: Any) -> Any:
    """A copy of a nested dict/list structure with every string scrubbed (see :func:`scrub`)."""
    if isinstance(node, str):
        return scrub(node)
    if isinstance(node, dict):
        return {k: scrub_tree(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return type(node)(scrub_tree(v) for v in node)
    return node


def scrub_file(path: str | Path) -> bool:
    """Rewrite a text file in place (atomically) without passwords; return whether it held one.

    The file keeps its permissions: the rewrite is done through a temp file beside it."""
    from lbo.core.atomic import write_text

    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError):
        return False
    clean = scrub(text)
    if clean == text:
        return False
    write_text(path, clean)
    return True
