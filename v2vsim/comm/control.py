"""Control traffic between the processes of a run (world, done, ack, start, static, vis, scan, bye,
hello): who may send what, and, with comm.auth on, a signed envelope: version 1 an HMAC-SHA256 under the
run's shared key (membership: any key holder can sign as anyone), version 2 the sending process's own
Ed25519 signature (comm.auth.identity per_process, v2vsim.comm.identity: a process can sign only as itself).

Without a signature anyone who can reach the bus could end a run with a 2-byte `done`, so
under comm.auth every control message travels as

    "<4sBQB" magic b"V2VC", version, sequence number, sender-name length
    sender name (utf-8, the process name: "driver.main", "cav.<id>", "ego.<id>")
    payload
    tag: version 1: 32 bytes hmac-sha256(key, domain | run id | kind | sender name | sequence | payload)
         version 2: 64 bytes, the named sender's Ed25519 signature over the same bytes

The tag covers the run id and the kind, so nothing from another run is accepted and a signed
`ack` cannot be replayed as `done`; the sequence number (strictly increasing per sender and
kind, checked by `ReplayGuard`) stops a recorded message from being played back in the same
run; a number more than MAX_SEQ_STEP past the last one is refused, so that one forged number cannot
make the real sender's next messages look replayed. `ControlPolicy` says which processes may send each
kind (world/done/start/static only the driver, ack only egos, vis and scan only CAVs, hello and bye
anyone of the run); it is applied with and without a key (without one, to the sender named in the
zenoh key, which is all there is to go on).
Failures raise codec.RejectedMessage with a reason from codec.REASONS.
"""

from __future__ import annotations

import hashlib
import hmac
import struct
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from v2vsim.comm.codec import SIG_LEN, TAG_LEN, RejectedMessage
from v2vsim.comm.identity import Identity
from v2vsim.comm.signing import Signer
from v2vsim.world.serialize import MAX_STATIC_BYTES, MAX_WORLD_BYTES

CONTROL_KINDS = frozenset({"world", "done", "ack", "start", "static", "vis", "scan", "bye", "hello"})
DRIVER = "driver.main"
CTRL_MAGIC = b"V2VC"
CTRL_VERSION = 1  # hmac-sha256 under the shared run key
CTRL_VERSION_IDENTITY = 2  # the sender's Ed25519 signature
MAX_SEQ_STEP = 1 << 16  # a sender sends far fewer control messages of one kind between two a receiver hears
_HEAD = struct.Struct("<4sBQB")
_DOMAIN = b"v2vsim control v1\0"  # keeps these tags apart from the data messages' tags
ENVELOPE_BYTES = _HEAD.size + 0xFF + max(SIG_LEN, TAG_LEN)
"""The most a signed envelope adds to a control payload (header, a 255-byte name, the tag)."""
MAX_CONTROL_BYTES = 4096
"""done, ack, start, hello, bye: a few dozen bytes of JSON (a bye's reason is cut at 200 characters)."""


def max_payload_bytes(kind: str) -> int | None:
    """The longest payload of a control kind a receiver accepts (None: the receiver's own bound, e.g. vis and scan,
    which depend on the scenario). Checked on arrival before the message is copied off the transport."""
    if kind in ("vis", "scan"):
        return None
    return {"world": MAX_WORLD_BYTES, "static": MAX_STATIC_BYTES}.get(kind, MAX_CONTROL_BYTES)


def process_id(name: str) -> str:
    """'ego.cav0' -> 'cav0': the sender chunk of the zenoh keys that process publishes on."""
    return name.split(".", 1)[-1]


@dataclass(frozen=True)
class ControlPolicy:
    """The process names allowed to send each control kind."""

    senders: Mapping[str, frozenset[str]]

    @classmethod
    def for_run(cls, cavs: Iterable[str], egos: Iterable[str]) -> ControlPolicy:
        driver = frozenset({DRIVER})
        cav_names = frozenset(f"cav.{c}" for c in cavs)
        ego_names = frozenset(f"ego.{e}" for e in egos)
        return cls({"world": driver, "done": driver, "start": driver, "static": driver,
                    "ack": ego_names, "vis": cav_names, "scan": cav_names, "bye": driver | cav_names | ego_names,
                    "hello": driver | cav_names | ego_names})

    def allows(self, kind: str, name: str) -> bool:
        return name in self.senders.get(kind, frozenset())

    def allows_key_sender(self, kind: str, sender: str) -> bool:
        """Whether some process allowed to send `kind` publishes under key chunk `sender`."""
        return any(process_id(n) == sender for n in self.senders.get(kind, frozenset()))


def _signed_bytes(run_id: str, kind: str, sender: str, seq: int, payload: bytes) -> bytes:
    parts = [_DOMAIN]
    for part in (run_id, kind, sender):
        b = part.encode("utf-8")
        parts.append(struct.pack("<H", len(b)) + b)
    parts += [struct.pack("<Q", seq), payload]
    return b"".join(parts)


def _tag(key: bytes, run_id: str, kind: str, sender: str, seq: int, payload: bytes) -> bytes:
    return hmac.new(key, _signed_bytes(run_id, kind, sender, seq, payload), hashlib.sha256).digest()


def seal(key: Signer, run_id: str, kind: str, sender: str, seq: int, payload: bytes) -> bytes:
    """The signed envelope of one control message from process `sender` (e.g. 'driver.main'): under the
    shared key (version 1) or, for an Identity, with that process's own signature (version 2)."""
    name = sender.encode("utf-8")
    if len(name) > 0xFF:
        raise ValueError(f"process name longer than 255 bytes: {sender[:40]!r}...")
    if isinstance(key, Identity):
        if key.name != sender:
            raise ValueError(f"{key.name} cannot sign as {sender}")
        return _HEAD.pack(CTRL_MAGIC, CTRL_VERSION_IDENTITY, seq, len(name)) + name + payload + key.sign(
            _signed_bytes(run_id, kind, sender, seq, payload))
    return _HEAD.pack(CTRL_MAGIC, CTRL_VERSION, seq, len(name)) + name + payload + _tag(
        key, run_id, kind, sender, seq, payload)


@dataclass(frozen=True)
class Opened:
    sender: str  # process name, e.g. 'driver.main'
    seq: int
    payload: bytes


def open_sealed(key: Signer, run_id: str, kind: str, key_sender: str, data: bytes,
                policy: ControlPolicy | None = None) -> Opened:
    """Verify an envelope that arrived on v2vsim/<run_id>/<kind>/<key_sender>; RejectedMessage if not.
    Under an Identity only version 2 (a process signature, checked with the named sender's public key from
    the trust list) is accepted; under a shared key only version 1."""
    if data[:4] != CTRL_MAGIC:
        raise RejectedMessage("unsigned", "comm.auth is on and the control message carries no envelope")
    if len(data) < _HEAD.size:
        raise RejectedMessage("truncated", f"{len(data)} bytes")
    _, version, seq, nlen = _HEAD.unpack_from(data)
    per_process = isinstance(key, Identity)
    want = CTRL_VERSION_IDENTITY if per_process else CTRL_VERSION
    if version != want:
        raise RejectedMessage("bad_version", f"control version {version}, this run signs with version {want}")
    tag_len = SIG_LEN if per_process else TAG_LEN
    if len(data) < _HEAD.size + nlen + tag_len:
        raise RejectedMessage("truncated", f"{len(data)} bytes")
    try:
        sender = data[_HEAD.size:_HEAD.size + nlen].decode("utf-8")
    except UnicodeDecodeError:
        raise RejectedMessage("bad_header", "sender name is not utf-8") from None
    payload, tag = data[_HEAD.size + nlen:-tag_len], data[-tag_len:]
    if isinstance(key, Identity):
        ok = key.verify(sender, _signed_bytes(run_id, kind, sender, seq, payload), tag)
    else:
        ok = hmac.compare_digest(_tag(key, run_id, kind, sender, seq, payload), tag)
    if not ok:
        raise RejectedMessage("bad_signature", f"{kind} from {sender!r}")
    if process_id(sender) != key_sender or (policy is not None and not policy.allows(kind, sender)):
        raise RejectedMessage("unknown_sender", f"{kind} from {sender!r} under key sender {key_sender!r}")
    return Opened(sender, seq, payload)


class ReplayGuard:
    """Per (sender, kind), sequence numbers must increase: a played-back message is 'replayed'."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, str], int] = {}
        self._lock = threading.Lock()

    def check(self, kind: str, opened: Opened) -> None:
        with self._lock:
            last = self._last.get((opened.sender, kind), -1)
            if opened.seq <= last:
                raise RejectedMessage("replayed", f"{kind} #{opened.seq} from {opened.sender!r}, last #{last}")
            if opened.seq > last + MAX_SEQ_STEP:  # forged far ahead: believing it would silence the real sender
                raise RejectedMessage("out_of_window", f"{kind} #{opened.seq} from {opened.sender!r}, last #{last}")
            self._last[(opened.sender, kind)] = opened.seq
