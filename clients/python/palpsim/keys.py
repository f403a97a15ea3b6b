"""CURVE keys and client identity for talking to a palpsim-server that encrypts
(palpsim-server --curve-secret, --allow; docs/security.md).

    keys = CurveKeys.from_files("server.key", "alice.key_secret")
    with Client("tcp://host:7420", curve=keys) as c: ...

Key files are what palpsim-keys writes: NAME.key holds a z85 public key, NAME.key_secret
the z85 secret key (the public half is derived from it). Lines that are blank or start
with '# ' are comments ('#' alone is also a z85 character, so a key may begin with it).
A key of the wrong half (the server's secret key as --server-key, a public key as
--client-key) and a client pair that does not match are refused, naming the file.
"""

from __future__ import annotations

import argparse
import re
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


# palpsim-keys writes "# palpsim CURVE public key 'NAME'" or "... secret key ..." above each key
_KIND_COMMENT = re.compile(r"^\s*# palpsim CURVE (public|secret) key")


def _key_lines(path: Path) -> list[tuple[int, str, str | None, int]]:
    """The key lines of a file: (line, key, the half palpsim-keys' comment above it names
    or None, that comment's line); raises KeyFileError for text after a key."""
    try:
        lines = path.read_text().splitlines()
    except OSError as e:
        raise KeyFileError(f"{path}: cannot read: {e.strerror}") from None
    keys = []
    marked, marked_line = None, 0
    for n, line in enumerate(lines, 1):
        m = _KIND_COMMENT.match(line)
        if m:
            marked, marked_line = m.group(1), n
            continue
        words = line.split()
        if not words or words[0] == "#":
            continue
        if len(words) > 1 and not words[1].startswith("#"):
            raise KeyFileError(f"{path}:{n}: not a key: text after the key that is not a '# ' comment")
        keys.append((n, words[0], marked, marked_line))
        marked = None
    return keys


def _name_half(path: Path) -> str | None:
    """The half a file's name gives: NAME.key_secret secret, NAME.key public."""
    if path.name.endswith(".key_secret"):
        return "secret"
    if path.name.endswith(".key"):
        return "public"
    return None


def read_key_file(path: str | Path, half: str | None = None) -> bytes:
    """The one z85 key of a key file (comments and blank lines skipped); raises KeyFileError
    naming the file and line when there is none, more than one, or it is not a z85 key.

    `half` ("public" or "secret") refuses a key of the other half: nothing in a z85 key
    tells, so palpsim-keys' comment above it does ("# palpsim CURVE secret key ..."), else
    the file's name (NAME.key public, NAME.key_secret secret). Given the wrong half a
    client speaks with another key, and a CURVE server never answers it."""
    path = Path(path)
    keys = _key_lines(path)
    if len(keys) != 1:
        raise KeyFileError(f"{path}: {'no key' if not keys else 'a second key on line %d' % keys[1][0]}; "
                           f"a key file holds one z85 key of {Z85_KEY_LENGTH} characters")
    n, key, marked, marked_line = keys[0]
    if len(key) != Z85_KEY_LENGTH or not set(key) <= _Z85:
        raise KeyFileError(f"{path}:{n}: not a key: {len(key)} characters, a z85 CURVE key has "
                           f"{Z85_KEY_LENGTH} of the z85 alphabet")
    kind = marked or _name_half(path)
    if half and kind and kind != half:
        why = (f"palpsim-keys marked it so on line {marked_line}" if marked
               else f"its name ends in {'.key_secret' if kind == 'secret' else '.key'}")
        want = ("give the public half, the NAME.key that palpsim-keys wrote beside NAME.key_secret"
                if half == "public" else "give NAME.key_secret, the file palpsim-keys wrote beside NAME.key")
        raise KeyFileError(f"{path}: a {kind} key ({why}), not a {half} key: {want}")
    return key.encode()


def read_secret_key_file(path: str | Path, public_path: str | Path | None = None) -> tuple[bytes, bytes]:
    """(secret, public) of a secret key file, the public half derived from the secret.
    Refuses a public key (read_key_file's `half`), and a pair that does not match: the
    public key file `public_path`, or without one NAME.key beside NAME.key_secret when
    there is one, must hold the public half of this secret. Raises KeyFileError naming
    the file(s)."""
    path = Path(path)
    secret = read_key_file(path, half="secret")
    public = zmq.curve_public(secret)
    if public_path is None and path.name.endswith(".key_secret"):
        beside = path.with_name(path.name[: -len("_secret")])
        public_path = beside if beside.exists() else None
    if public_path is not None:
        given = read_key_file(public_path, half="public")
        if given != public:
            raise KeyFileError(f"{path} and {public_path} are not a pair: the public half of {path} is "
                               f"{public.decode()}, {public_path} holds {given.decode()} (one of them was "
                               f"replaced: make a new pair with palpsim-keys NAME --force and hand out the "
                               f"new NAME.key)")
    return secret, public


@dataclass(frozen=True)
class CurveKeys:
    """What a client needs to speak CURVE: the server's public key and its own pair (z85)."""

    server_public: bytes
    client_public: bytes
    client_secret: bytes

    @classmethod
    def from_files(cls, server_key: str | Path, client_key: str | Path) -> "CurveKeys":
        """The server's NAME.key and this client's NAME.key_secret; raises KeyFileError
        naming a bad file (a key of the wrong half, a client pair that does not match:
        read_secret_key_file), RuntimeError when this pyzmq has no CURVE."""
        if not zmq.has("curve"):
            raise RuntimeError("this pyzmq's libzmq has no CURVE (zmq.has('curve') is false)")
        secret, public = read_secret_key_file(client_key)
        return cls(server_public=read_key_file(server_key, half="public"), client_public=public,
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
