"""The peer topology's credentials: the run's TLS authority, one certificate per process, access control by name."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import stat

import pytest

from testbed.common.errors import BadInput
from testbed.wire import transport


def test_a_tls_folder_has_an_authority_without_its_key_and_one_certificate_per_process(tmp_path):
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

    d = transport.TlsCredentials.new(tmp_path / "tls").folder
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    names = sorted(os.listdir(d))
    assert names == sorted(["ca.pem"] + [f"{u}.{e}" for u in transport.USERS for e in ("pem", "key")])
    keys = [n for n in names if (d / n).read_bytes().find(b"PRIVATE KEY") >= 0]
    assert keys == sorted(f"{u}.key" for u in transport.USERS)  # the authority's key was never written
    for k in keys:
        assert stat.S_IMODE((d / k).stat().st_mode) == 0o600
    ca = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for u in transport.USERS:
        cert = x509.load_pem_x509_certificate((d / f"{u}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value == u
        assert cert.issuer == ca.subject
        ca.public_key().verify(cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm))
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    with pytest.raises(FileExistsError):
        transport.TlsCredentials.new(d)  # never overwritten


def test_two_folders_are_two_authorities(tmp_path):
    a = transport.TlsCredentials.new(tmp_path / "a").folder
    b = transport.TlsCredentials.new(tmp_path / "b").folder
    assert (a / "ca.pem").read_bytes() != (b / "ca.pem").read_bytes()


def test_a_session_reads_only_safe_files_of_its_own(tmp_path):
    d = transport.TlsCredentials.new(tmp_path / "tls").folder
    t = transport.TlsCredentials(d).zenoh("plant")
    assert t["enable_mtls"] is True and t["listen_private_key"].endswith("plant.key")
    assert t["root_ca_certificate"].endswith("ca.pem") and t["connect_certificate"].endswith("plant.pem")
    os.chmod(d / "encoder.key", 0o644)
    with pytest.raises(BadInput, match="readable by others"):
        transport.TlsCredentials(d).zenoh("encoder")
    (d / "attacker.pem").unlink()
    with pytest.raises(BadInput, match="attacker.pem"):
        transport.TlsCredentials(d).zenoh("attacker")
    (d / "controller.pem").write_bytes(b"")
    with pytest.raises(BadInput, match="not a PEM file"):
        transport.TlsCredentials(d).zenoh("controller")
    with pytest.raises(BadInput, match="nobody.pem"):
        transport.TlsCredentials(d).zenoh("nobody")


def test_a_tls_session_speaks_tls_only_and_checks_by_certificate_name(tmp_path):
    d = transport.TlsCredentials.new(tmp_path / "tls").folder
    keys = transport.Keys.for_run("r")
    acl = transport.acl_config(keys, by="cert_common_names")
    assert {s["id"]: s for s in acl["subjects"]}["plant"] == {"id": "plant", "cert_common_names": ["plant"]}
    assert acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["publish_encoder"]["key_exprs"] == [f"testbed/r/{k}" for k in transport.publish_keys("encoder")]
    with pytest.raises(ValueError):
        transport.acl_config(keys, by="zids")
    c = transport.make_config(mode="peer", acl=acl, tls=transport.TlsCredentials(d).zenoh("plant"))
    assert json.loads(c.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(c.get_json("listen/endpoints")) == [transport.TLS_LOOPBACK_ANY]
    assert json.loads(c.get_json("transport/link/tls/enable_mtls")) is True


def test_a_node_of_the_peer_topology_needs_tls_endpoints(tmp_path):
    from testbed.wire.session import SessionOptions, zenoh_config

    d = transport.TlsCredentials.new(tmp_path / "tls").folder
    base = SessionOptions(topology="peer", tls_dir=str(d))
    keys = transport.Keys.for_run("r")
    conf = zenoh_config(base, "plant", keys, hub=True)  # standalone: the plant listens on 7447, TLS
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/127.0.0.1:7447"]
    conf = zenoh_config(base, "encoder", keys)
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    with pytest.raises(BadInput, match="mutual TLS"):
        zenoh_config(dataclasses.replace(base, connect=("tcp/127.0.0.1:7447",)), "encoder", keys)
    with pytest.raises(BadInput, match="--tls-dir"):
        zenoh_config(dataclasses.replace(base, tls_dir=None), "encoder", keys)


def test_topology_auto_is_peer_on_one_host_and_router_when_a_node_may_be_elsewhere(tmp_path):
    """``testbed run --topology auto`` (the default): peer exactly when every node runs on the launcher's host."""
    from testbed.commands.liveconfig import run_config
    from testbed.commands.run import add_arguments_run
    from testbed.live.credentials import ONE_HOST, choose_topology

    p = argparse.ArgumentParser()
    add_arguments_run(p)

    def choice(*flags):
        return choose_topology(run_config(p.parse_args(["paper", *flags])))

    assert p.parse_args(["paper"]).topology == "auto"
    assert choice() == ("peer", ONE_HOST)
    assert choice("--listen", "tls/127.0.0.1:7447", "--node-listen", "plant=tls/[::1]:0")[0] == "peer"
    assert choice("--listen", "tls/localhost:7447")[0] == "peer"
    assert choice("--insecure", "--listen", "tcp/127.0.0.1:7447")[0] == "peer"  # plain TCP is the insecure peer's
    assert choice("--tls-dir", str(tmp_path), "--node-prefix", "plant=ssh hostB")[0] == "peer"  # its certificates
    for flags, why in [
        (("--node-prefix", "plant=ip netns exec tb-plant"), "--node-prefix plant"),
        (("--node-prefix", "controller=ssh hostB", "--insecure"), "another host"),
        (("--secret-file", str(tmp_path / "run.secret")), "password file"),
        (("--zenoh-config", str(tmp_path / "z.json5")), "--zenoh-config"),
        (("--listen", "tls/10.0.0.1:7447"), "not a loopback address"),
        (("--listen", "tls/0.0.0.0:7447"), "not a loopback address"),
        (("--node-connect", "tls/hostA:7447"), "not a loopback address"),
        (("--node-listen", "plant=tls/10.0.0.2:0"), "--node-listen"),
        (("--listen", "tcp/127.0.0.1:7447"), "plain TCP"),
    ]:
        topology, reason = choice(*flags)
        assert topology == "router" and why in reason, (flags, reason)
    assert choice("--topology", "router") == ("router", "--topology router")
    assert choice("--topology", "peer", "--node-prefix", "plant=ssh hostB")[0] == "peer"
