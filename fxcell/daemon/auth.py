"""The daemon's bearer token: generated at first start, stored owner-only, overridable.

Every request that changes the robot must carry ``Authorization: Bearer <token>``.
The token comes from the environment variable ``FXCELL_TOKEN`` when set, else from the
token file (``daemon.token_file``, default ``~/.config/fxcell/token``), which the
daemon creates with mode 0600 (its directory 0700) the first time it starts.
"""

from __future__ import annotations

import hmac
import os
import secrets
import stat
from pathlib import Path

from fxcell.errors import ConfigError

TOKEN_ENV = "FXCELL_TOKEN"
MIN_REMOTE_TOKEN_LENGTH = 16


def token_path(path: str | Path) -> Path:
    return Path(path).expanduser()


def read_token(path: str | Path) -> str | None:
    """The token clients should send: ``$FXCELL_TOKEN``, else the token file, else ``None``."""
    env = os.environ.get(TOKEN_ENV)
    if env:
        return env.strip()
    try:
        text = token_path(path).read_text().strip()
    except OSError:
        return None
    return text or None


def load_or_create_token(path: str | Path) -> str:
    """The daemon's token; creates the token file (owner-only) on first use.

    An existing token file readable by group or others is refused: whoever can read it
    can move the robot.
    """
    env = os.environ.get(TOKEN_ENV)
    if env is not None:
        if not env.strip():
            raise ConfigError(f"{TOKEN_ENV} is set but empty")
        return env.strip()
    file = token_path(path)
    try:
        mode = file.stat().st_mode
    except FileNotFoundError:
        return _create(file)
    except OSError as exc:
        raise ConfigError(f"daemon.token_file: cannot read {file}: {exc.strerror}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(
            f"daemon.token_file: {file} is accessible by other users "
            f"(mode {stat.S_IMODE(mode):o}); run: chmod 600 {file}"
        )
    token = file.read_text().strip()
    if not token:
        raise ConfigError(f"daemon.token_file: {file} is empty; delete it to generate a new token")
    return token


def _create(file: Path) -> str:
    token = secrets.token_urlsafe(32)
    try:
        file.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as exc:
        raise ConfigError(f"daemon.token_file: cannot create {file}: {exc.strerror}") from None
    with os.fdopen(fd, "w") as out:
        out.write(token + "\n")
    return token


def check_bearer(header: str | None, token: str) -> bool:
    """Whether an ``Authorization`` header carries ``token`` (constant-time comparison)."""
    if not header:
        return False
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer":
        return False
    return hmac.compare_digest(value.strip().encode(), token.encode())
