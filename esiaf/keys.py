"""CURVE key pairs for ZeroMQ across hosts (``esiaf keys DIR``), and loading them at start-up.

``esiaf keys DIR [--component NAME ...]`` writes, with ``zmq.auth.create_certificates``::

    DIR/orchestrator.key          the orchestrator's public key: every component needs it
    DIR/orchestrator.key_secret   the orchestrator's key pair: its host only
    DIR/NAME.key, NAME.key_secret a component key pair (NAME = component unless --component)
    DIR/clients/NAME.key          the public keys the orchestrator (and every producer) accepts

Every process with ``ESIAF_CURVE_DIR=DIR`` speaks CURVE instead of PLAIN on ZeroMQ: the
orchestrator loads ``orchestrator.key_secret``, a component its key pair ``ESIAF_CURVE_KEY``
(default ``component``) and ``orchestrator.key``; every server socket (the orchestrator's, a
producer's audio output) accepts only the keys in ``DIR/clients/``. ``esiaf.auth.secure_socket``
makes a CURVE client of a socket, :func:`server` a server. A missing, unreadable or wrong key file
is a :class:`KeyFileError` with one line, at start-up. Existing files are never overwritten: run
again with new names to add components, and copy their ``NAME.key`` into the ``clients/`` of every
process that is to let them in; SIGHUP makes a process read its ``clients/`` again
(:func:`reload_clients`: the orchestrator's sockets, a producer's audio output, the producers a
consumer connects to), no restart needed.
"""
from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq
import zmq.auth
from zmq.utils import z85

log = logging.getLogger(__name__)

CURVE_DIR_ENV = "ESIAF_CURVE_DIR"
CURVE_KEY_ENV = "ESIAF_CURVE_KEY"
ORCHESTRATOR = "orchestrator"
COMPONENT = "component"
CLIENTS = "clients"
KEY_CHARS = 40  # a CURVE key in Z85
# Why a server socket refused a peer's handshake, as its socket monitor says: auth, the ZAP handler
# said no (a key or token not allowed); protocol, another mechanism (e.g. no keys at all); other, it
# ended mid-handshake (a peer without keys, at times).
HANDSHAKE_FAILURES: dict[int, str] = {zmq.EVENT_HANDSHAKE_FAILED_AUTH: "auth",
                                      zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL: "protocol",
                                      zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL: "other"}


class KeyFileError(Exception):
    """A CURVE key file is missing, unreadable or not what it should be: one line saying which."""


@dataclass(frozen=True)
class Curve:
    """This process's CURVE keys (Z85)."""

    public: bytes
    secret: bytes
    orchestrator: bytes  # the orchestrator's public key: the server key of its sockets
    clients_dir: Path  # the public keys (*.key) of the clients our servers accept
    clients: frozenset[bytes]  # ... as loaded at start-up


def _check_key(key: bytes | None, path: Path) -> bytes:
    if key is None or len(key) != KEY_CHARS or not set(key) <= set(z85.Z85CHARS):
        raise KeyFileError(f"{path}: not a {KEY_CHARS}-character Z85 CURVE key "
                           "(make key files with: esiaf keys DIR)")
    return key


def _read(path: Path) -> tuple[bytes, bytes | None]:
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        reason = exc.strerror.lower() if isinstance(exc, OSError) and exc.strerror else "no public key in it"
        if not path.exists():
            reason = "no such file"
        raise KeyFileError(f"cannot read the CURVE key file {path}: {reason} ({CURVE_DIR_ENV}; "
                           f"esiaf keys {path.parent} makes it)") from None
    return _check_key(public, path), secret


def key_pair(path: Path) -> tuple[bytes, bytes]:
    """The (public, secret) keys of a ``.key_secret`` file."""
    public, secret = _read(path)
    if secret is None:
        raise KeyFileError(f"{path} holds a public key only: this process needs its key pair "
                           f"(the .key_secret file esiaf keys made)")
    _check_key(secret, path)
    if zmq.curve_public(secret) != public:
        raise KeyFileError(f"{path}: its public and secret keys do not belong together")
    return public, secret


def allowed_clients(directory: Path) -> frozenset[bytes]:
    """The public keys of the ``*.key`` files in ``directory``: at least one."""
    if not directory.is_dir():
        raise KeyFileError(f"{directory} is not a directory: it holds the public keys of the allowed "
                           f"clients (esiaf keys {directory.parent} makes it)")
    found = frozenset(_read(path)[0] for path in sorted(directory.glob("*.key")))
    if not found:
        raise KeyFileError(f"no public key (*.key) in {directory}: no client could connect")
    return found


def load(orchestrator: bool, env: Mapping[str, str] = os.environ) -> Curve | None:
    """This process's keys if ``ESIAF_CURVE_DIR`` is set, else None (PLAIN with the token): the
    orchestrator's key pair, or a component's (``ESIAF_CURVE_KEY``, default ``component``), the
    orchestrator's public key and the allowed clients."""
    directory = env.get(CURVE_DIR_ENV, "").strip()
    if not directory:
        return None
    root = Path(directory)
    if not root.is_dir():
        raise KeyFileError(f"{CURVE_DIR_ENV}={directory} is not a directory (esiaf keys {directory} makes one)")
    name = ORCHESTRATOR if orchestrator else (env.get(CURVE_KEY_ENV, "").strip() or COMPONENT)
    public, secret = key_pair(root / f"{name}.key_secret")
    server_key = public if orchestrator else _read(root / f"{ORCHESTRATOR}.key")[0]
    return Curve(public, secret, server_key, root / CLIENTS, allowed_clients(root / CLIENTS))


def reload_clients(curve: Curve | None, authenticator: Any = None) -> frozenset[bytes] | None:
    """Reads the allowed client keys (``curve.clients_dir``) again, on SIGHUP, and gives them to
    ``authenticator`` (a pyzmq ZAP handler, if this process serves any socket): the new set, or None
    without CURVE keys or if a key file cannot be read (logged, never fatal: the old set stays)."""
    if curve is None:
        log.info("event=keys_not_reloaded reason=no CURVE keys (ESIAF_CURVE_DIR) in use")
        return None
    try:
        allowed = allowed_clients(curve.clients_dir)
        if authenticator is not None:
            authenticator.configure_curve(domain="*", location=str(curve.clients_dir))
    except (OSError, ValueError, KeyFileError) as exc:
        log.error("event=keys_not_reloaded dir=%s reason=%s", curve.clients_dir, exc)
        return None
    log.info("event=keys_reloaded dir=%s clients=%d", curve.clients_dir, len(allowed))
    return allowed


def server(socket: zmq.Socket, curve: Curve) -> None:
    """Makes ``socket`` a CURVE server with this process's key pair (a ZAP handler picks clients)."""
    socket.curve_secretkey = curve.secret
    socket.curve_publickey = curve.public
    socket.curve_server = True


def make(directory: Path, components: Sequence[str]) -> tuple[list[Path], list[Path]]:
    """Makes the orchestrator's and the components' key pairs that are not there yet; returns the
    files (made, kept). Secret files are readable by their owner only."""
    (directory / CLIENTS).mkdir(parents=True, exist_ok=True)
    made, kept = [], []
    for name in (ORCHESTRATOR, *components):
        secret_file = directory / f"{name}.key_secret"
        if secret_file.exists() or (directory / f"{name}.key").exists():
            kept.append(secret_file)
        else:
            public_path, secret_path = zmq.auth.create_certificates(directory, name)
            os.chmod(secret_path, 0o600)
            made += [Path(public_path), Path(secret_path)]
        if name != ORCHESTRATOR:
            shutil.copyfile(directory / f"{name}.key", directory / CLIENTS / f"{name}.key")
    return made, kept


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="esiaf keys", description="make CURVE key pairs for ZeroMQ across hosts")
    parser.add_argument("directory", type=Path, help="where the key files go (made if absent)")
    parser.add_argument("--component", action="append", default=[], metavar="NAME",
                        help="a key pair of its own for this component (repeatable; default: one pair, "
                             "'component', for all)")
    args = parser.parse_args(argv)
    names = args.component or [COMPONENT]
    bad = [name for name in names if not name or name == ORCHESTRATOR or "/" in name or name.startswith(".")]
    if bad:
        parser.error(f"not a component name: {', '.join(repr(name) for name in bad)}")
    try:
        made, kept = make(args.directory, names)
    except OSError as exc:
        print(f"esiaf keys: cannot write in {args.directory}: {exc.strerror}", file=sys.stderr)
        return 2
    root = args.directory.resolve()
    for path in made:
        print(f"made {path}")
    for path in kept:
        print(f"kept {path} (already there)")
    which = (f"every component uses the pair '{COMPONENT}' (the default of {CURVE_KEY_ENV})" if names == [COMPONENT]
             else f"each component {CURVE_KEY_ENV}=NAME, its pair: {', '.join(names)}")
    print(f"""
Orchestrator host: {root}/{ORCHESTRATOR}.key_secret and {root}/{CLIENTS}/ (the allowed components).
Each component's host: {root}/{ORCHESTRATOR}.key, its own NAME.key_secret and {CLIENTS}/.
Give every process {CURVE_DIR_ENV}={root}; {which}.
Never copy a .key_secret to a host other than its owner's.""")
    return 0
