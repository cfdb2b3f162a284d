"""Results and ``end_of_stream`` notices bound to the registration that sends them.

A message on the results plane is four frames: ``[kind, body, key_id, mac]``. ``key_id`` names the
registration (the orchestrator gives it with the ``control_key``, a new pair for every
registration) and ``mac`` is HMAC-SHA256, keyed with the ``control_key``, of ``kind``, a zero byte
and ``body``. The body names its component (a result's ``instance``, a notice's ``component_id``);
the orchestrator refuses the message unless the MAC is the one that component's registration makes.

A MAC rather than the key itself: the key never travels on the results plane (nor sits in a socket
queue, a capture or a log line of a refused message), and the MAC covers the body, so a message
cannot be altered or have its name changed on the way. The orchestrator derives each control key
from a secret it keeps in its database, the component id and the key id (:func:`derive_key`): after
a restart it can still check what an instance sent under a registration made before it (results
queued while it was away), and nobody can make a key for an id without that secret.
"""
from __future__ import annotations

import base64
import hashlib
import hmac
from typing import Protocol

MAC_BYTES = hashlib.sha256().digest_size
MAX_KEY_ID_BYTES = 64


class Registered(Protocol):
    key_id: str
    control_key: str


def mac(control_key: str, kind: bytes, body: bytes) -> bytes:
    return hmac.new(control_key.encode(), kind + b"\0" + body, hashlib.sha256).digest()


def signed(kind: bytes, body: bytes, registration: Registered | None) -> list[bytes]:
    """The frames to send: ``[kind, body]`` with the registration's key id and MAC (none before a
    registration, or from an orchestrator that gave no key id: the message is then refused)."""
    if registration is None or not registration.key_id:
        return [kind, body]
    return [kind, body, registration.key_id.encode(), mac(registration.control_key, kind, body)]


def derive_key(secret: bytes, component_id: str, key_id: str) -> str:
    """The control key of registration ``key_id`` of ``component_id`` (the orchestrator's side)."""
    digest = hmac.new(secret, f"{component_id}\0{key_id}".encode(), hashlib.sha256).digest()
    return base64.urlsafe_b64encode(digest).rstrip(b"=").decode()
