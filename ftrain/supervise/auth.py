"""The per-run secret of several nodes, and the signed lines their supervisors exchange with node 0.

Every request and every reply is one line, ``<HMAC-SHA256 in hex> <JSON>``, at most ``MAX_MESSAGE`` bytes; the
MAC covers the JSON and whether it is a request or a reply (a reply cannot pass for a request). A request carries
a fresh nonce that its reply repeats, so an old reply cannot pass for a new one. The secret comes from
``FTRAIN_RDZV_SECRET`` or from the file ``--rdzv-secret-file`` names, the same on every node.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import socket
import time
from pathlib import Path

from ftrain.errors import UserError

SECRET_ENV = "FTRAIN_RDZV_SECRET"
MIN_SECRET = 16
"""Characters a secret must have at least."""
MAX_MESSAGE = 4096
"""Bytes of one line, newline included; a longer one is refused unread."""
REQUEST, REPLY = b"request", b"reply"
HOW_TO_SET = (
    f"set {SECRET_ENV} to the same random string on every node (e.g. $(openssl rand -hex 32)), "
    "or pass --rdzv-secret-file FILE holding it"
)


class Refused(ConnectionError):
    """A line that is not a well-formed, correctly signed message of this run; the text says why. A connection
    error to the node that asked: node 0 counts as unreachable until it answers properly."""


def load_secret(secret_file: str, environ: dict[str, str]) -> bytes:
    """The run's secret from ``secret_file`` (if given) or the environment; UserError if missing or short."""
    if secret_file:
        try:
            secret = Path(secret_file).read_text().strip()
        except OSError as error:
            raise UserError(f"--rdzv-secret-file={secret_file!r} cannot be read ({error.strerror})") from None
        where = f"--rdzv-secret-file={secret_file!r}"
    else:
        secret = environ.get(SECRET_ENV, "").strip()
        where = SECRET_ENV
    if not secret:
        raise UserError(f"several nodes need a shared secret for node 0's coordinator: {HOW_TO_SET}")
    if len(secret) < MIN_SECRET:
        raise UserError(f"{where} holds {len(secret)} characters, fewer than {MIN_SECRET}: {HOW_TO_SET}")
    return secret.encode()


def seal(secret: bytes, kind: bytes, body: dict) -> bytes:
    """One signed line carrying ``body``."""
    data = json.dumps(body, separators=(",", ":")).encode()
    return _mac(secret, kind, data).encode() + b" " + data + b"\n"


def unseal(secret: bytes, kind: bytes, line: bytes) -> dict:
    """The body of a signed line (without its newline); Refused unless the signature is right and it is a mapping."""
    mac, _, data = line.partition(b" ")
    try:
        mac_text = mac.decode("ascii")
    except UnicodeDecodeError:
        raise Refused("malformed") from None
    if len(mac_text) != 64:
        raise Refused("malformed")
    if not hmac.compare_digest(mac_text, _mac(secret, kind, data)):
        raise Refused("bad signature")
    try:
        body = json.loads(data)
    except ValueError:
        raise Refused("malformed") from None
    if not isinstance(body, dict):
        raise Refused("malformed")
    return body


def read_line(sock: socket.socket, timeout: float) -> bytes:
    """One line from ``sock`` within ``timeout`` seconds in all, without its newline; Refused if it takes longer,
    grows past ``MAX_MESSAGE`` or the peer closes first."""
    deadline = time.monotonic() + timeout
    data = b""
    while b"\n" not in data:
        if len(data) >= MAX_MESSAGE:
            raise Refused("oversized")
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise Refused("too slow")
        sock.settimeout(remaining)
        try:
            chunk = sock.recv(MAX_MESSAGE - len(data))
        except TimeoutError:
            raise Refused("too slow") from None
        if not chunk:
            raise Refused("closed before a whole message")
        data += chunk
    line = data.partition(b"\n")[0]
    if len(line) >= MAX_MESSAGE:
        raise Refused("oversized")
    return line


def _mac(secret: bytes, kind: bytes, data: bytes) -> str:
    return hmac.new(secret, kind + b"\n" + data, hashlib.sha256).hexdigest()
