"""The run's certificates: made by a forked child while the launcher goes on, or by the launcher itself when
that child fails (``testbed.live.credentials``); real certificates, a real fork."""

from __future__ import annotations

import os
import types
from pathlib import Path

import pytest

from testbed.live.credentials import RunCredentials
from testbed.wire import transport


class _Run(RunCredentials):
    """The credentials of a launcher of the peer topology with no --tls-dir: it makes the run's own."""

    def __init__(self, run_dir: Path):
        cfg = types.SimpleNamespace(topology="peer", tls_dir=None, secret_file=None, insecure=False, listen=None,
                                    node_connect=None, node_listen={})
        super().__init__(cfg, "test-run", transport.Keys.for_run("test-run"))
        assert self.secure and self.tls
        self.run_dir = run_dir

    def make_secrets(self) -> None:
        super().make_secrets(self.run_dir)


def _usable(folder: Path) -> None:
    """Every process's key and certificate is there, of one authority (what a session is opened with)."""
    for who in transport.USERS:
        assert transport.TlsCredentials(folder).zenoh(who)
    assert oct((folder / "ca.pem").stat().st_mode & 0o777) == "0o644" and oct(folder.stat().st_mode & 0o777) == "0o700"


def test_the_child_makes_the_certificates_while_the_launcher_goes_on(tmp_path):
    run = _Run(tmp_path)
    run.make_secrets()
    assert run._tls_maker is not None and run.tls_dir.parent == run.secret_dir
    run.secrets_ready()
    assert run._tls_maker is None
    _usable(run.tls_dir)
    run.remove_secrets()
    assert not run.secret_dir.exists()


def test_a_failed_child_leaves_the_launcher_to_make_them(tmp_path, monkeypatch):
    """The child dies half way (a half-made folder): the launcher removes what it left and makes them itself."""
    real = transport.TlsCredentials.new.__func__
    launcher = os.getpid()

    def fails_in_the_child(cls, folder, users=transport.USERS):
        if os.getpid() != launcher:
            Path(folder).mkdir(mode=0o700)
            (Path(folder) / "ca.pem").write_text("half")
            raise OSError("no space left on device")
        return real(cls, folder, users)

    monkeypatch.setattr(transport.TlsCredentials, "new", classmethod(fails_in_the_child))
    run = _Run(tmp_path)
    run.make_secrets()
    assert run._tls_maker is not None
    run.secrets_ready()
    _usable(run.tls_dir)
    run.remove_secrets()
    assert not run.secret_dir.exists()


def test_credentials_never_used_are_removed_and_the_child_reaped(tmp_path):
    """A run refused or interrupted between making and using them: no child left, no folder left."""
    run = _Run(tmp_path)
    run.make_secrets()
    pid = run._tls_maker
    run.remove_secrets()
    assert run._tls_maker is None and not run.secret_dir.exists()
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)
