"""CURVE keys and client identity for talking to a palpsim-server that encrypts
(palpsim-server --curve-secret, --allow; README "Security").

    keys = CurveKeys.from_files("server.key", "alice.key_secret")
    with Client("tcp://host:7420", curve=keys) as c: ...

Key files are what palpsim-keys writes: NAME.key holds a z85 public key, NAME.key_secret
the z85 secret key (the public half is derived from it). Lines that are blank or start
with '# ' are comments ('#' alone is also a z85 character, so a key may begin with it).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import zmq

Z85_KEY_LENGTH = 40
_Z85 = set("0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#")

# what a client adds when a server stays silent, with CURVE and without (a refused
# handshake is silent on the client's side)
SILENCE_HINT = (" (with CURVE a server also stays silent when --server-key is not its public key, "
                "when this client's key is not on its allow-list, or when it runs without keys)")
PLAIN_SILENCE_HINT = (" (a server with keys also stays silent to a client without them: give "
                      "--server-key and --client-key)")


def silence_hint(curve: "CurveKeys | None") -> str:
    """The hint for a silent server, by whether the client speaks CURVE."""
    return SILENCE_HINT if curve is not None else PLAIN_SILENCE_HINT


class KeyFileError(ValueError):
    """A key file that cannot be used; the message names the file and line."""


def read_key_file(path: str | Path) -> bytes:
    """The one z85 key of a key file (comments and blank lines skipped); raises KeyFileError
    naming the file and line when there is none, more than one, or it is not a z85 key."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as e:
        raise KeyFileError(f"{path}: cannot read: {e.strerror}") from None
    keys = []
    for n, line in enumerate(lines, 1):
        words = line.split()
        if not words or words[0] == "#":
            continue
        if len(words) > 1 and not words[1].startswith("#"):
            raise KeyFileError(f"{path}:{n}: not a key: text after the key that is not a '# ' comment")
        keys.append((n, words[0]))
    if len(keys) != 1:
        raise KeyFileError(f"{path}: {'no key' if not keys else 'a second key on line %d' % keys[1][0]}; "
                        f"a key file holds one z85 key of {Z85_KEY_LENGTH} characters")
    n, key = keys[0]
    if len(key) != Z85_KEY_LENGTH or not set(key) <= _Z85:
        raise KeyFileError(f"{path}:{n}: not a key: {len(key)} characters, a z85 CURVE key has "
                        f"{Z85_KEY_LENGTH} of the z85 alphabet")
    return key.encode()


@dataclass(frozen=True)
class CurveKeys:
    """What a client needs to speak CURVE: the server's public key and its own pair (z85)."""

    server_public: bytes
    client_public: bytes
    client_secret: bytes

    @classmethod
    def from_files(cls, server_key: str | Path, client_key: str | Path) -> "CurveKeys":
        """The server's NAME.key and this client's NAME.key_secret; raises KeyFileError
        naming a bad file, RuntimeError when this pyzmq has no CURVE."""
        if not zmq.has("curve"):
            raise RuntimeError("this pyzmq's libzmq has no CURVE (zmq.has('curve') is false)")
        secret = read_key_file(client_key)
        return cls(server_public=read_key_file(server_key), client_public=zmq.curve_public(secret),
                   client_secret=secret)

    def apply(self, sock: zmq.Socket) -> None:
        """Makes `sock` a CURVE client of the server (before connect)."""
        sock.curve_serverkey = self.server_public
        sock.curve_publickey = self.client_public
        sock.curve_secretkey = self.client_secret


def add_arguments(p: argparse.ArgumentParser, token: bool = True) -> None:
    """Adds --server-key, --client-key and (with `token`: for tools that act on sessions
    other tools opened) --client-token to a command line."""
    g = p.add_argument_group("who this client is (README, \"Security\")")
    g.add_argument("--server-key", metavar="FILE",
                   help="the server's public key (its NAME.key from palpsim-keys): speak CURVE")
    g.add_argument("--client-key", metavar="FILE",
                   help="this client's secret key (NAME.key_secret), whose public key the server "
                        "allows; sessions opened with it belong to that key")
    if token:
        g.add_argument("--client-token", metavar="TEXT", default="",
                       help="without CURVE: act as the client that opened sessions with this token "
                            "(e.g. watch a haptic client's session); ignored with CURVE")


def from_arguments(args: argparse.Namespace) -> CurveKeys | None:
    """The CurveKeys of --server-key and --client-key (None without them); raises
    KeyFileError when only one is given or a file is bad."""
    if bool(args.server_key) != bool(args.client_key):
        raise KeyFileError("--server-key and --client-key go together (CURVE needs both)")
    return CurveKeys.from_files(args.server_key, args.client_key) if args.server_key else None
