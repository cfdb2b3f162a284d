"""The shared token every component presents to the orchestrator (``Authorization: Bearer``).

It comes from ``ESIAF_TOKEN``, or from the file ``ESIAF_TOKEN_FILE`` names (a Docker secret, say);
with neither, no token is sent and an orchestrator without a token accepts that. ``esiaf run``
makes a new one per run (``<workdir>/token``) and hands it to every service it starts.
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path

TOKEN_ENV = "ESIAF_TOKEN"
TOKEN_FILE_ENV = "ESIAF_TOKEN_FILE"
ZMQ_USER = "esiaf"  # the ZAP PLAIN user name; the token is the password


class TokenError(Exception):
    pass


def token() -> str:
    """This process's token ('' if none is configured)."""
    value = os.environ.get(TOKEN_ENV, "").strip()
    if value:
        return value
    path = os.environ.get(TOKEN_FILE_ENV, "").strip()
    if not path:
        return ""
    try:
        return Path(path).read_text().strip()
    except OSError as exc:
        raise TokenError(f"cannot read the token file {path} ({TOKEN_FILE_ENV}): {exc.strerror}") from None


def headers() -> dict[str, str]:
    """The HTTP (and websocket) headers that carry the token, if there is one."""
    value = token()
    return {"Authorization": f"Bearer {value}"} if value else {}


def new_token() -> str:
    return secrets.token_urlsafe(24)


def write_token(path: Path, value: str) -> None:
    """Writes the token readable by its owner only (curl -H "Authorization: Bearer $(cat ...)")."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.touch(mode=0o600, exist_ok=True)
    os.chmod(path, 0o600)
    path.write_text(value + "\n")


def secure_socket(socket) -> None:
    """Makes a ZeroMQ socket that connects to the orchestrator present the token (ZAP PLAIN)."""
    value = token()
    if value:
        socket.plain_username = ZMQ_USER.encode()
        socket.plain_password = value.encode()
