"""Is a result or an ``end_of_stream`` notice from the registration it names? (esiaf/binding.py)

The message must carry a key id and a MAC of its kind and body keyed with the control key of the
component it names (a result's ``instance``, a notice's ``component_id``):

- a live or departed (dead) component: its registration's key id and key; a key id of one of its
  earlier registrations (it registered again since, with a new key) is accepted too: only that
  instance was given it, and what it signed while it registered again (a long decode starved its
  heartbeat, it was declared dead and came back) must not be lost;
- a component we do not know (registered before a restart of ours): the key derived from our
  secret, its id and the key id, so only a key we gave can make the MAC;
- with CURVE keys, it must also come with the public key its registration is bound to (the one of
  its first accepted message, on either plane).

Every comparison is constant-time. The reasons are those of the ingest counters' ``refused_*``.
"""
from __future__ import annotations

import hmac

import zmq

from esiaf.binding import MAC_BYTES, MAX_KEY_ID_BYTES, derive_key, mac

from ..registry.components import Registry


def refusal(registry: Registry, frames: list[bytes], component_id: str, peer_key: str | None) -> str | None:
    """None if ``frames`` (``[kind, body, key_id, mac]``) prove they come from ``component_id``'s
    registration, else the reason to refuse them. ``peer_key``: its CURVE public key, with CURVE."""
    if len(frames) != 4:
        return "no_key"
    kind, body, key_id, tag = frames
    if not 0 < len(key_id) <= MAX_KEY_ID_BYTES or len(tag) != MAC_BYTES or not key_id.isascii():
        return "bad_key"
    component = registry.get(component_id) or registry.departed.get(component_id)
    if component is None or not hmac.compare_digest(key_id, component.key_id.encode()):
        derived = derive_key(registry.secret, component_id, key_id.decode())
        proven = hmac.compare_digest(mac(derived, kind, body), tag)
        if component is None:
            return None if proven else "wrong_key"
        # a registration of this id that we gave, but not its current one: it registered again since,
        # and this was signed before (the same instance: accepted, nothing it sent is lost)
        return None if proven else "wrong_key"
    if not hmac.compare_digest(mac(component.control_key, kind, body), tag):
        return "wrong_key"
    if peer_key is not None:
        if not peer_key:
            return "wrong_peer_key"
        if component.control_peer_key is None:
            component.control_peer_key = peer_key
        elif not hmac.compare_digest(peer_key.encode(), component.control_peer_key.encode()):
            return "wrong_peer_key"
    return None


def peer_key(frames: list[zmq.Frame]) -> str:
    """With CURVE, the public key a message came with (Z85: what pyzmq's ZAP handler names it)."""
    try:
        return str(frames[0].get("User-Id"))
    except (zmq.ZMQError, IndexError):
        return ""  # no metadata: bound to no registration
