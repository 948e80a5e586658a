"""Per-process identity under `comm.auth.identity: per_process` (issue 34): who signed a message, not
only that some key holder did.

Signed V2X (IEEE 1609.2, ETSI TS 103 097) gives every station its own key pair and a certificate from
an authority that receivers check. Scaled down to one run: the runner is the run's authority. For every
process of the run (driver.main, cav.<id>, ego.<id>) it makes a fresh Ed25519 key pair and hands the
process its private key and the run's trust list (process name -> public key) out of band: over the
child's stdin pipe for a local process, or as an identity file (mode 0600) for an agent started on
another host, which the operator carries there (docs/cluster.md). Nothing of it ever travels on the bus,
so a process that holds its own key can sign only as itself: a receiver verifies every signature with
the public key of the process the message claims to come from.

Threat model (docs/run.md "Trust between processes"): defended against any process on the bus,
including one that holds another process's credentials for *its own* name (a compromised CAV signing as
the driver, another CAV or an ego) and the zenoh router (it can drop or delay, not forge or replay);
not defended: a process that can read another's private key (the same user reading the runner's
memory or an identity file it was not given), and denial of service by volume (bounded, not prevented:
agents/ego_mailbox.py).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import secrets
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.serialization import Encoding, NoEncryption, PrivateFormat, PublicFormat

SIG_LEN = 64  # Ed25519
FORMAT = "v2vsim-identity-1"


class IdentityError(ValueError):
    """An identity document that cannot be read: says which and why."""


@dataclass(frozen=True)
class Identity:
    """One process's credentials for one run: its name, its private key, and the run's trust list."""

    run_id: str
    name: str  # the process name: 'driver.main', 'cav.<id>', 'ego.<id>'
    private: Ed25519PrivateKey
    trust: Mapping[str, Ed25519PublicKey]  # every process of the run, this one included

    def sign(self, data: bytes | memoryview) -> bytes:
        return self.private.sign(bytes(data))

    def verify(self, signer: str, data: bytes | memoryview, signature: bytes | memoryview) -> bool:
        """Whether `signature` over `data` is process `signer`'s (False for a process not of this run)."""
        pub = self.trust.get(signer)
        if pub is None:
            return False
        try:
            pub.verify(bytes(signature), bytes(data))
            return True
        except InvalidSignature:
            return False

    def to_json(self) -> str:
        """The document the runner hands the process (its private key inside: keep it off the bus and disk)."""
        raw = self.private.private_bytes(Encoding.Raw, PrivateFormat.Raw, NoEncryption())
        return json.dumps({"format": FORMAT, "run_id": self.run_id, "name": self.name, "private_key": _b64(raw),
                           "trust": {n: _b64(p.public_bytes(Encoding.Raw, PublicFormat.Raw))
                                     for n, p in sorted(self.trust.items())}})


def new_run_instance() -> str:
    """A fresh, unguessable name for one start of a run (16 hex digits): what binds signatures under a shared
    key to this run instance, whatever its run id."""
    return secrets.token_hex(8)


def shared_run_key(secret: bytes, run_id: str, instance: str) -> bytes:
    """The key every process signs with under comm.auth.key_file: HMAC-SHA256 of the file's secret over the run
    id and the run instance. A message captured from an earlier run with the same key file and --run-id was
    signed under another instance's key, so it fails the signature check here (issue 45 case 4)."""
    return hmac.new(secret, b"v2vsim-run-instance\0" + run_id.encode() + b"\0" + instance.encode(),
                    hashlib.sha256).digest()


def data_signer(sender_id: str) -> str:
    """The process that signs a V2V data message of sender id `sender_id` (a CAV's perception agent)."""
    return f"cav.{sender_id}"


def issue(run_id: str, names: Iterable[str]) -> dict[str, Identity]:
    """The runner's job as the run's authority: a fresh key pair per process and one trust list for all."""
    keys = {n: Ed25519PrivateKey.generate() for n in names}
    trust = {n: k.public_key() for n, k in keys.items()}
    return {n: Identity(run_id, n, k, trust) for n, k in keys.items()}


def write_identity_file(path: Path, identity: Identity) -> None:
    """An identity for an agent on another host, readable by its owner only (created 0600, never widened)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(identity.to_json())


def parse_identity(text: str, where: str, *, run_id: str, name: str) -> Identity:
    """The Identity in a document from the runner; IdentityError naming `where` and what is wrong."""
    try:
        doc = json.loads(text)
    except ValueError as e:
        raise IdentityError(f"{where}: not an identity document (JSON: {e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise IdentityError(f"{where}: not an identity document (format must be {FORMAT!r})")
    if doc.get("run_id") != run_id:
        raise IdentityError(f"{where}: issued for run {doc.get('run_id')!r}, this is run {run_id!r}")
    if doc.get("name") != name:
        raise IdentityError(f"{where}: issued to {doc.get('name')!r}, this process is {name!r}")
    try:
        private = Ed25519PrivateKey.from_private_bytes(_unb64(doc["private_key"]))
        trust = {str(n): Ed25519PublicKey.from_public_bytes(_unb64(p)) for n, p in dict(doc["trust"]).items()}
    except (KeyError, TypeError, ValueError) as e:
        raise IdentityError(f"{where}: a key is missing or malformed ({type(e).__name__}: {e})") from None
    mine = private.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
    listed = trust.get(name)
    if listed is None or listed.public_bytes(Encoding.Raw, PublicFormat.Raw) != mine:
        raise IdentityError(f"{where}: the trust list does not carry this process's public key")
    return Identity(run_id, name, private, trust)


def _b64(b: bytes) -> str:
    return base64.b64encode(b).decode("ascii")


def _unb64(s: str) -> bytes:
    return base64.b64decode(s.encode("ascii"), validate=True)
