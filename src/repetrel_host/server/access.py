"""Who may use the server: its own API key, the app keys a person granted (OctoPrint's
appkeys plugin), and the sessions of OctoPrint's login.

The server has one user, its owner (:data:`OWNER`): the server's key and every app key
act as that user, as a user's own key does on OctoPrint (a farm manager takes OctoPrint's
``_api`` user for "not logged in"). App keys live in the data folder (``appkeys.json``,
0600), so ``hyrel-server keys list|revoke`` works beside a running server: the server
reads the file again whenever it changed.

A one-time link (``hyrel-server link``) is an app key's request that a person allowed in
advance: whoever can write the data folder makes one (``links.json``, beside the keys), and
the first browser that opens it within its time gets the app key, once. The file keeps a
link's SHA-256 only: the link itself is in nobody's files."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import hmac
import json
import os
import secrets
import time
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from ipaddress import IPv4Network, IPv6Network, ip_address
from pathlib import Path
from typing import Any, TypeVar

OWNER = "admin"
GROUPS = ("admins", "users")
# OctoPrint 1.11's permissions (octoprint/access/permissions.py): the owner has them all.
PERMISSIONS = (
    "ADMIN STATUS CONNECTION WEBCAM SYSTEM FILES_LIST FILES_UPLOAD FILES_DOWNLOAD "
    "FILES_DELETE FILES_SELECT PRINT GCODE_VIEWER MONITOR_TERMINAL CONTROL SLICE "
    "TIMELAPSE_LIST TIMELAPSE_DOWNLOAD TIMELAPSE_DELETE TIMELAPSE_MANAGE_UNRENDERED "
    "TIMELAPSE_ADMIN SETTINGS_READ SETTINGS PLUGIN_APPKEYS_GRANT PLUGIN_APPKEYS_ADMIN"
).split()
KEYS_FILE = "appkeys.json"
LINKS_FILE = "links.json"
LINK_SECONDS = 600.0  # a one-time link stays good this long unless told otherwise
LINK_LONGEST = 24 * 3600.0  # and this long at most
# A link used or expired is remembered this long after its end, to say which it was.
LINK_REMEMBERED = 24 * 3600.0
LINK_UNKNOWN = (
    "this link is not one the server made, or it ended over a day ago: make a new one "
    "(hyrel-server link)"
)
LINK_USED = (
    "this link was used already: a one-time link opens the page once; make a new one "
    "(hyrel-server link)"
)
LINK_EXPIRED = "this link has expired: make a new one (hyrel-server link) and open it in time"
# OctoPrint's appkeys: a request not polled for 5 s is dropped (the app gave up), and
# none lives longer than 10 minutes.
POLL_TIMEOUT = 5.0
REQUEST_CUTOFF = 600.0
DECISION_KEPT = 600.0  # a decision waits this long for the app's next poll
SESSIONS_KEPT = 1000  # logins remembered; the least recently used go first
SESSION_IDLE = 7 * 24 * 3600.0  # a session unused this long is gone


@dataclass(frozen=True)
class AppKey:
    """A key granted to an application (``app``), acting as ``user``."""

    app: str
    key: str
    user: str = OWNER
    created: float = field(default_factory=time.time)


@dataclass(frozen=True)
class PageLink:
    """A one-time link to the page, as the data folder keeps it: its token's SHA-256, the
    app key's name it grants, and its times (seconds since the epoch: it crosses processes)."""

    digest: str
    app: str
    expires: float
    made: float = field(default_factory=time.time)
    used: float | None = None


class LinkRefused(Exception):
    """A one-time link that opens nothing (unknown, used or expired): the sentence says which."""


@dataclass
class Request:
    """An application's request for a key, waiting for a person's decision."""

    app: str
    app_token: str
    user_token: str
    remote: str
    user: str | None
    created: float = field(default_factory=time.monotonic)
    polled: float = field(default_factory=time.monotonic)
    granted: str | None = None  # the key, once a person allowed it
    decided: float | None = None

    def public(self) -> dict[str, str]:
        """As OctoPrint lists a pending decision."""
        return {
            "app_id": self.app,
            "user_id": self.user or OWNER,
            "user_token": self.user_token,
            "remote_address": self.remote,
        }


class Access:
    """The server's key, the app keys, the pending requests and the login sessions."""

    def __init__(
        self,
        data_dir: Path,
        api_key: str,
        public_read: bool = False,
        trusted: Sequence[IPv4Network | IPv6Network] = (),
    ) -> None:
        self.api_key = api_key
        self.public_read = public_read
        # Moonraker's trusted clients: its face lets these addresses in without a key.
        self.trusted = tuple(trusted)
        self.path = data_dir / KEYS_FILE
        self._keys: list[AppKey] = []
        self._seen: tuple[int, int] | None = None  # the file's (mtime, size) when read
        self._requests: list[Request] = []
        self._sessions: OrderedDict[str, tuple[str, float]] = OrderedDict()

    # --- keys -----------------------------------------------------------------------------

    def user_for_key(self, key: str) -> str | None:
        """Whose key ``key`` is: the owner's for the server's key or an app key; None."""
        if not key:
            return None
        if hmac.compare_digest(key.encode(), self.api_key.encode()):
            return OWNER
        for granted in self.app_keys():
            if hmac.compare_digest(key.encode(), granted.key.encode()):
                return granted.user
        return None

    def trusts(self, host: str | None) -> bool:
        """``host`` (a client's address) is in a trusted network."""
        if not self.trusted or not host:
            return False
        try:
            address = ip_address(host)
        except ValueError:
            return False
        return any(address in network for network in self.trusted)

    def app_keys(self) -> list[AppKey]:
        """The app keys, as the file holds them now."""
        try:
            stat = self.path.stat()
        except FileNotFoundError:
            self._keys, self._seen = [], None
            return []
        seen = stat.st_mtime_ns, stat.st_size
        if seen != self._seen:
            self._keys, self._seen = read_keys(self.path), seen
        return list(self._keys)

    def grant(self, app: str, user: str = OWNER) -> AppKey:
        """A new key for ``app`` (its earlier key, if any, is replaced)."""
        return grant(self.path, app, user)

    def revoke(self, app: str) -> bool:
        """Forget the keys of ``app``; False when it had none."""
        return revoke(self.path, app)

    # --- requests (OctoPrint's appkeys flow) ------------------------------------------------

    def request(self, app: str, remote: str, user: str | None = None) -> Request:
        self._expire()
        pending = Request(app, secrets.token_urlsafe(24), secrets.token_urlsafe(24), remote, user)
        self._requests.append(pending)
        return pending

    def poll(self, app_token: str) -> Request | None:
        """The request behind ``app_token`` (its poll noted), or None when it is unknown,
        denied or expired. A granted request is answered once, then forgotten."""
        self._expire()
        for pending in self._requests:
            if hmac.compare_digest(pending.app_token, app_token):
                pending.polled = time.monotonic()
                if pending.granted is not None:
                    self._requests.remove(pending)
                return pending
        return None

    def pending(self) -> list[Request]:
        """The requests waiting for a decision."""
        self._expire()
        return [p for p in self._requests if p.decided is None]

    def decide(self, user_token: str, allow: bool, user: str = OWNER) -> Request | None:
        """A person's decision; None when there is no such request (any more)."""
        self._expire()
        for pending in self._requests:
            if pending.decided is None and hmac.compare_digest(pending.user_token, user_token):
                pending.decided = time.monotonic()
                if allow:
                    pending.granted = self.grant(pending.app, user).key
                else:
                    self._requests.remove(pending)
                return pending
        return None

    def _expire(self) -> None:
        now = time.monotonic()

        def alive(pending: Request) -> bool:
            if pending.decided is not None:
                return now - pending.decided < DECISION_KEPT
            return now - pending.polled < POLL_TIMEOUT and now - pending.created < REQUEST_CUTOFF

        self._requests = [p for p in self._requests if alive(p)]

    # --- sessions (OctoPrint's login) --------------------------------------------------------

    def login(self, user: str) -> str:
        """A new session for ``user``."""
        session = secrets.token_hex(16)
        self._sessions[session] = (user, time.monotonic())
        while len(self._sessions) > SESSIONS_KEPT:
            self._sessions.popitem(last=False)
        return session

    def user_for_session(self, session: str) -> str | None:
        """Whose session ``session`` is (and it was used now); None when unknown."""
        known = self._sessions.get(session) if session else None
        if known is None:
            return None
        user, used = known
        now = time.monotonic()
        if now - used > SESSION_IDLE:
            del self._sessions[session]
            return None
        self._sessions[session] = (user, now)
        self._sessions.move_to_end(session)
        return user

    def logout(self, session: str) -> None:
        self._sessions.pop(session, None)


def read_keys(path: Path) -> list[AppKey]:
    """The app keys kept in ``path`` (none when it is missing)."""
    return _read(path, AppKey)


def grant(path: Path, app: str, user: str = OWNER) -> AppKey:
    """A new key for ``app``, kept in ``path`` (its earlier key, if any, is replaced)."""
    granted = AppKey(app, secrets.token_urlsafe(32), user)
    with _locked(path, AppKey) as keys:
        keys[:] = [k for k in keys if (k.app, k.user) != (app, user)] + [granted]
    return granted


def revoke(path: Path, app: str) -> bool:
    """Remove the keys of ``app`` from ``path``; False when it had none."""
    with _locked(path, AppKey) as keys:
        kept = [k for k in keys if k.app != app]
        found = len(kept) != len(keys)
        keys[:] = kept
    return found


def make_page_link(
    data_dir: Path, app: str | None = None, seconds: float = LINK_SECONDS
) -> tuple[str, PageLink]:
    """A one-time link for the data folder ``data_dir`` (its token, and the link as kept):
    good for ``seconds``, it grants the app key ``app`` (default: "page link", the time and
    four hex digits) to the first browser that opens it."""
    token = secrets.token_urlsafe(16)
    # The default name is one of its own: opening a link replaces the key of its name.
    named = app or f"page link {time.strftime('%Y-%m-%d %H:%M:%S')} #{secrets.token_hex(2)}"
    made = PageLink(_digest(token), named, time.time() + seconds)
    with _locked(data_dir / LINKS_FILE, PageLink) as links:
        links[:] = [*_remembered(links), made]
    return token, made


def redeem_page_link(data_dir: Path, token: str) -> AppKey:
    """The app key that the one-time link ``token`` grants, granted now; the link is spent.
    :class:`LinkRefused` says why not (unknown, used, expired)."""
    digest = _digest(token)
    with _locked(data_dir / LINKS_FILE, PageLink) as links:
        links[:] = _remembered(links)
        found = next(
            (n for n, link in enumerate(links) if hmac.compare_digest(link.digest, digest)), None
        )
        if found is None:
            raise LinkRefused(LINK_UNKNOWN)
        link = links[found]
        if link.used is not None:
            raise LinkRefused(LINK_USED)
        if link.expires <= time.time():
            raise LinkRefused(LINK_EXPIRED)
        links[found] = replace(link, used=time.time())
        # Within the links' lock: a link is spent if and only if its key was granted.
        return grant(data_dir / KEYS_FILE, link.app)


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def _remembered(links: list[PageLink]) -> list[PageLink]:
    """The links still good, or ended (used, expired) less than a day ago."""
    now = time.time()
    return [n for n in links if now - (n.expires if n.used is None else n.used) < LINK_REMEMBERED]


Kept = TypeVar("Kept", AppKey, PageLink)


def _read(path: Path, kind: type[Kept]) -> list[Kept]:
    try:
        entries: list[dict[str, Any]] = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    return [kind(**entry) for entry in entries]


@contextlib.contextmanager
def _locked(path: Path, kind: type[Kept]) -> Iterator[list[Kept]]:
    """The entries in ``path`` to change, written back atomically (0600) under a lock, so
    that the server and ``hyrel-server keys`` or ``link`` never lose each other's change.
    An exception in the block leaves the file as it was."""
    with open(path.with_suffix(".lock"), "w") as lock:
        _as_the_folders(path.with_suffix(".lock"))
        fcntl.flock(lock, fcntl.LOCK_EX)
        entries = _read(path, kind)
        yield entries
        partial = path.with_suffix(".part")
        descriptor = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(descriptor, "w") as out:
            json.dump([asdict(entry) for entry in entries], out, indent=1)
        _as_the_folders(partial)
        partial.replace(path)


def _as_the_folders(path: Path) -> None:
    """Give ``path`` to the data folder's owner, the server's user, when root made it
    (``sudo hyrel-server link`` beside a service): else the server could not open it again."""
    if os.geteuid() == 0:
        folder = path.parent.stat()
        os.chown(path, folder.st_uid, folder.st_gid)
