"""The shared token every component presents to the orchestrator (``Authorization: Bearer``).

It comes from ``ESIAF_TOKEN``, or from the file ``ESIAF_TOKEN_FILE`` names (a Docker secret, say);
with neither, no token is sent and an orchestrator without a token accepts that. ``esiaf run``
makes a new one per run (``<workdir>/token``) and hands it to every service it starts.
On ZeroMQ the token is a PLAIN password, in clear text: across hosts, CURVE keys (esiaf/keys.py)
take its place. Over HTTPS (the orchestrator's ``tls_cert``) clients check its certificate against
the system's CAs, or the CA file ``ESIAF_TLS_CA`` names (a private CA, a self-signed certificate).
"""
from __future__ import annotations

import logging
import os
import re
import secrets
from pathlib import Path
from typing import Any

import httpx

from esiaf.keys import Curve

TOKEN_ENV = "ESIAF_TOKEN"
TOKEN_FILE_ENV = "ESIAF_TOKEN_FILE"
ZMQ_USER = "esiaf"  # the ZAP PLAIN user name; the token is the password
TLS_CA_ENV = "ESIAF_TLS_CA"


class TokenError(Exception):
    pass


def token() -> str:
    """This process's token ('' if none is configured). A token file that cannot be read or is empty,
    and a token that an HTTP header cannot carry (a space or a control character in it), are a
    TokenError, one line: never a run without the token that was meant."""
    value = os.environ.get(TOKEN_ENV, "").strip()
    where = TOKEN_ENV
    if not value:
        path = os.environ.get(TOKEN_FILE_ENV, "").strip()
        if not path:
            return ""
        where = f"the token file {path} ({TOKEN_FILE_ENV})"
        try:
            value = Path(path).read_text().strip()
        except (OSError, UnicodeDecodeError) as exc:
            reason = exc.strerror if isinstance(exc, OSError) else "not text"
            raise TokenError(f"cannot read {where}: {reason}") from None
        if not value:
            raise TokenError(f"{where} is empty")
    if not all("!" <= char <= "~" for char in value):
        raise TokenError(f"{where}: a token is printable ASCII without spaces (esiaf run makes one if none is given)")
    return value


class RedactTokens(logging.Filter):
    """Takes tokens out of every record a handler writes: the value of ``token=`` in a URL (the
    dashboard's websocket, in uvicorn's lines), what follows ``Bearer``, and the token's own value
    wherever it stands, in the message and in a traceback."""

    PATTERN = re.compile(r"(?i)(token=|bearer\s+)[^\s&\"'<>;,)]+")

    def __init__(self, value: str = "") -> None:
        super().__init__()
        self.value = value

    def redact(self, text: str) -> str:
        text = self.PATTERN.sub(r"\1[redacted]", text)
        return text.replace(self.value, "[redacted]") if len(self.value) >= 4 else text

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        redacted = self.redact(message)
        if redacted != message:
            record.msg, record.args = redacted, None
        if record.exc_info and not record.exc_text:
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = self.redact(record.exc_text)
        return True


def redact_logs(value: str = "") -> None:
    """Adds :class:`RedactTokens` (with ``value``, by default this process's token) to every handler of
    the root logger: call it once logging is configured."""
    try:
        value = value or token()
    except TokenError:
        value = ""
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, RedactTokens) for f in handler.filters):
            handler.addFilter(RedactTokens(value))


def tls_context() -> Any:
    """An ``ssl.SSLContext`` that checks the orchestrator's HTTPS certificate against ``ESIAF_TLS_CA``
    if set, else the system's CAs. A CA file that cannot be read is a TokenError, one line."""
    context = httpx.create_ssl_context()
    cafile = os.environ.get(TLS_CA_ENV, "").strip()
    if cafile:
        try:
            context.load_verify_locations(cafile=cafile)
        except OSError as exc:  # ssl.SSLError is one
            raise TokenError(f"cannot read the CA file {cafile} ({TLS_CA_ENV}): {exc.strerror or exc}") from None
    return context


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


def secure_socket(socket, curve: Curve | None = None, server_key: bytes | None = None) -> None:
    """Makes a ZeroMQ socket that connects to a server of ours authenticate: with this process's
    CURVE keys if ``curve`` (the server's public key is the orchestrator's unless ``server_key``
    is given), else with the token (ZAP PLAIN), if there is one."""
    if curve is not None:
        socket.curve_secretkey = curve.secret
        socket.curve_publickey = curve.public
        socket.curve_serverkey = server_key or curve.orchestrator
        return
    value = token()
    if value:
        socket.plain_username = ZMQ_USER.encode()
        socket.plain_password = value.encode()
