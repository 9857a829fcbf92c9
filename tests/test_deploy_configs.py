"""Certificates (romannet/deploy/pki.py), the generated Zenoh configs (romannet/deploy/zenoh_configs.py), the
committed ones in deploy/zenoh/, `romannet deploy certs|configs` and the $ROMANNET_ZENOH_CONFIG default. No
network here: tests/test_deploy_secure.py runs the configs with real sessions."""

from __future__ import annotations

import json
import stat
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from romannet.cli import build_parser
from romannet.deploy.pki import common_name, generate_site
from romannet.deploy.zenoh_configs import SiteLayout, access_control, router_config, site_configs

ROOT = Path(__file__).resolve().parents[1]


def _cert(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_site_certificates_chain_to_the_ca_with_one_identity_each(tmp_path: Path) -> None:
    site = generate_site(tmp_path, ["actor-0", "robot-7"], ["10.0.0.2", "router.lab"])
    ca = _cert(site.ca_cert)
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert sorted(site.identities) == ["actor-0", "learner", "operator", "replay", "robot-7", "router"]
    for name, ident in site.identities.items():
        cert = _cert(ident.cert)
        cert.verify_directly_issued_by(ca)  # raises if the signature or issuer is wrong
        assert common_name(ident.cert) == name
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        usages = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert ExtendedKeyUsageOID.CLIENT_AUTH in usages and ExtendedKeyUsageOID.SERVER_AUTH in usages
        assert stat.S_IMODE(ident.key.stat().st_mode) == 0o600, name
    assert stat.S_IMODE(site.ca_key.stat().st_mode) == 0o600
    san = _cert(site["router"].cert).extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.2"]
    assert "router.lab" in san.get_values_for_type(x509.DNSName)


def test_generating_again_keeps_what_exists_and_reissues_what_must_change(tmp_path: Path) -> None:
    first = generate_site(tmp_path, ["actor-0"], ["10.0.0.2"])
    before = {n: i.cert.read_bytes() for n, i in first.identities.items()}
    ca_before = first.ca_cert.read_bytes()
    second = generate_site(tmp_path, ["actor-0", "actor-1"], ["10.0.0.2"])  # a new robot joins
    assert second.ca_cert.read_bytes() == ca_before
    assert all(second[n].cert.read_bytes() == before[n] for n in before)
    _cert(second["actor-1"].cert).verify_directly_issued_by(_cert(second.ca_cert))
    third = generate_site(tmp_path, ["actor-0", "actor-1"], ["10.0.0.2", "10.0.0.9"])  # the router moved
    assert third["router"].cert.read_bytes() != before["router"]
    assert third["actor-0"].cert.read_bytes() == before["actor-0"]
    forced = generate_site(tmp_path, ["actor-0", "actor-1"], ["10.0.0.2", "10.0.0.9"], force=True)
    assert forced["actor-0"].cert.read_bytes() != before["actor-0"]
    assert forced.ca_cert.read_bytes() == ca_before


@pytest.mark.parametrize("ids", [[], ["actor-0", "actor-0"], ["replay"], ["bad/id"]])
def test_bad_actor_ids_are_refused(tmp_path: Path, ids: list[str]) -> None:
    with pytest.raises(ValueError):
        generate_site(tmp_path, ids)
    with pytest.raises(ValueError):
        SiteLayout(actor_ids=tuple(ids), router_endpoints=("tls/h:1",), listen=("tls/h:1",), pki_dir="/p")


def test_a_profile_takes_only_its_own_kind_of_endpoint() -> None:
    with pytest.raises(ValueError, match="tls/"):
        SiteLayout(pki_dir="/etc/romannet/pki")  # the default endpoints are tcp/
    with pytest.raises(ValueError, match="tcp/"):
        SiteLayout(router_endpoints=("tls/h:7447",))


def test_every_generated_config_is_valid_for_the_installed_zenoh(tmp_path: Path) -> None:
    """zenoh's config parser is strict (unknown keys and values are errors), so loading each file checks
    every key of it against this zenoh version."""
    for layout in (SiteLayout(), SiteLayout(router_endpoints=("tls/r:7447",), listen=("tls/0.0.0.0:7447",),
                                            pki_dir="/etc/romannet/pki")):
        for name, text in site_configs(layout).items():
            path = tmp_path / name
            path.write_text(text)
            config = zenoh.Config.from_file(str(path))
            mode = json.loads(config.get_json("mode"))
            assert mode == ("router" if name == "router.json5" else "client"), name
            assert json.loads(config.get_json("scouting/multicast/enabled")) is False
            assert json.loads(config.get_json("transport/link/tx/lease")) == 3000
            tls = json.loads(config.get_json("transport/link/tls"))
            assert bool(tls["enable_mtls"]) == layout.secure, name


def test_the_policy_gives_each_actor_its_own_keys_only() -> None:
    acl = access_control(("actor-0", "actor-1"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert all(r["permission"] == "allow" for r in rules.values())
    policies = {p["subjects"][0]: [rules[i] for i in p["rules"]] for p in acl["policies"]}
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects == {n: [n] for n in ("replay", "learner", "operator", "actor-0", "actor-1")}
    for actor, other in (("actor-0", "actor-1"), ("actor-1", "actor-0")):
        keys = [k for r in policies[actor] for k in r["key_exprs"]]
        assert not any(other in k for k in keys), (actor, keys)
        assert "romannet/@v1/*/replay/insert/" + actor in keys
        sent = {m for r in policies[actor] if r["flows"] == ["ingress"] for m in r["messages"]}
        assert sent == {"query", "liveliness_token", "declare_subscriber", "declare_liveliness_subscriber",
                        "liveliness_query"}, sent  # never put, declare_queryable or reply
    publishers = {who for who, rs in policies.items() for r in rs if "put" in r["messages"] and
                  r["flows"] == ["ingress"] and any(k.endswith("/weights/announce") for k in r["key_exprs"])}
    assert publishers == {"learner"}
    servers = {who for who, rs in policies.items() for r in rs if "declare_queryable" in r["messages"]
               and any(k.endswith("/replay/sample") for k in r["key_exprs"])}
    assert servers == {"replay"}
    admin = {who for who, rs in policies.items() for r in rs if any(k.startswith("@") for k in r["key_exprs"])}
    assert admin == {"operator"}


@pytest.mark.parametrize("folder,layout", [
    ("deploy/zenoh", SiteLayout(router_endpoints=("tcp/romannet-router:7447",))),
    ("deploy/zenoh/secure", SiteLayout(router_endpoints=("tls/romannet-router:7447",), listen=("tls/0.0.0.0:7447",),
                                       pki_dir="/etc/romannet/pki")),
])
def test_committed_configs_are_what_the_generator_writes(folder: str, layout: SiteLayout) -> None:
    """deploy/zenoh/ is regenerated with `romannet deploy configs` (deploy/README.md); never edited by hand."""
    expected = site_configs(layout)
    committed = {p.name: p.read_text() for p in (ROOT / folder).glob("*.json5")}
    assert committed == expected


def test_router_config_enforces_block_for_the_fleet_keys() -> None:
    qos = router_config(SiteLayout())["qos"]["network"]
    assert qos == [{"id": "romannet-block", "messages": ["put", "query"], "key_exprs": ["romannet/@v1/**"],
                    "overwrite": {"congestion_control": "block"}}]


def test_deploy_certs_writes_a_site_and_says_where_each_file_goes(tmp_path: Path) -> None:
    out = tmp_path / "site"
    cmd = [sys.executable, "-m", "romannet.cli", "deploy", "certs", str(out), "--actors", "3", "--router-host",
           "10.1.2.3", "--install-dir", "/etc/romannet"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "actor-2: pki/actor-2.pem pki/actor-2.key zenoh/actor-2.json5" in done.stdout
    assert "keep pki/ca.key off" in done.stdout
    actor = json.loads(zenoh.Config.from_file(str(out / "zenoh" / "actor-2.json5")).get_json("transport/link/tls"))
    assert actor["connect_certificate"] == "/etc/romannet/pki/actor-2.pem"
    router = zenoh.Config.from_file(str(out / "zenoh" / "router.json5"))
    assert json.loads(router.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]
    client = zenoh.Config.from_file(str(out / "zenoh" / "replay.json5"))
    assert json.loads(client.get_json("connect/endpoints")) == ["tls/10.1.2.3:7447"]
    assert common_name(out / "pki" / "actor-2.pem") == "actor-2"
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)  # again: nothing re-issued
    assert done.returncode == 0 and common_name(out / "pki" / "actor-2.pem") == "actor-2"
    bad = subprocess.run([*cmd[:7], "0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--actors 0 is invalid" in bad.stderr


def test_services_read_the_zenoh_config_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROMANNET_ZENOH_CONFIG", "/etc/romannet/zenoh/actor-0.json5")
    parser = build_parser()
    for verb in (["replay", "--dir", "d"], ["learner", "--run-dir", "d"], ["actor", "--run-dir", "d"],
                 ["router"], ["deploy", "check", "--run-id", "r"]):
        assert parser.parse_args(verb).zenoh_config == "/etc/romannet/zenoh/actor-0.json5", verb
    assert parser.parse_args(["actor", "--run-dir", "d", "--zenoh-config", "x.json5"]).zenoh_config == "x.json5"
    monkeypatch.setenv("ROMANNET_ZENOH_CONFIG", "")
    assert build_parser().parse_args(["replay", "--dir", "d"]).zenoh_config is None
    monkeypatch.delenv("ROMANNET_ZENOH_CONFIG")
    assert build_parser().parse_args(["actor", "--run-dir", "d"]).zenoh_config is None
