"""The shipped router config (deploy/zenoh/router.json5: credentials and access control, TLS with
client certificates) in front of a real fusion process: only the depth role changes the map, and
each pair's depth user only its own pair's keys."""

import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from common.client import MapUnavailable, health, latest
from common.lattice import Window
from common.occupancy_map import UNKNOWN
from tests.conftest import PROCESS_LIFETIME_S, REPO, free_port, wait_for
from tests.tiles import tile_payload

pytestmark = pytest.mark.process

DEPLOY = REPO / "deploy"
PASSWORDS = {
    "camera": "pw-camera",
    "depth-p0": "pw-depth-p0",
    "depth-p1": "pw-depth-p1",
    "fusion": "pw-fusion",
    "robot": "pw-robot",
}
TILE = Window(0, 0, 20, 20)


def _client_config(
    path: Path, endpoint: str, certs: Path, user: str | None, password: str | None
) -> Path:
    """deploy/zenoh/client.json5 with this test's router, certificates and credentials."""
    config = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "client.json5"))
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(certs / "ca.pem")))
    config.insert_json5(
        "transport/link/tls/connect_certificate", json.dumps(str(certs / "box.pem"))
    )
    config.insert_json5(
        "transport/link/tls/connect_private_key", json.dumps(str(certs / "box-key.pem"))
    )
    if user is None:
        config.insert_json5("transport/auth/usrpwd", "{}")
    else:
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    path.write_text(str(config))
    return path


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("certs")
    subprocess.run(
        ["bash", str(DEPLOY / "make-certs.sh"), str(directory), "localhost", "box"],
        check=True,
        capture_output=True,
    )
    return directory


def shipped_router(endpoint: str, certs: Path, directory: Path) -> zenoh.Session:
    """deploy/zenoh/router.json5 in this process, on ``endpoint``: TLS with client certificates
    from ``certs``, the credentials of PASSWORDS, its access control."""
    credentials = directory / "credentials.txt"
    credentials.write_text("".join(f"{u}:{p}\n" for u, p in PASSWORDS.items()))
    config = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "router.json5"))
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials)))
    tls = {"root_ca_certificate": "ca.pem", "listen_certificate": "localhost.pem"}
    tls["listen_private_key"] = "localhost-key.pem"
    for key, name in tls.items():
        config.insert_json5(f"transport/link/tls/{key}", json.dumps(str(certs / name)))
    return zenoh.open(config)


@pytest.fixture(params=["tcp", "tls"])
def site(request: pytest.FixtureRequest, certs: Path, tmp_path: Path) -> Iterator[dict[str, Any]]:
    """The ACL router (in this process) and a fusion process connected as the fusion user."""
    endpoint = (
        f"tls/localhost:{free_port()}" if request.param == "tls" else f"tcp/127.0.0.1:{free_port()}"
    )
    router = shipped_router(endpoint, certs, tmp_path)
    fusion_config = _client_config(
        tmp_path / "fusion.json5", endpoint, certs, "fusion", PASSWORDS["fusion"]
    )
    command = ["timeout", "-s", "INT", "-k", "5", str(PROCESS_LIFETIME_S), sys.executable, "-m"]
    command += ["services.cli", "fusion", "--config", str(fusion_config)]
    fusion = subprocess.Popen(
        [*command, "--state-dir", str(tmp_path / "state")],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
    )

    def session(user: str | None, password: str | None = None) -> zenoh.Session:
        path = _client_config(tmp_path / f"{user}.json5", endpoint, certs, user, password)
        return zenoh.open(zenoh.Config.from_file(str(path)))

    try:
        robot = session("robot", PASSWORDS["robot"])
        wait_for(lambda: _answers(robot), 30, "fusion to answer through the router")
        yield {"session": session, "robot": robot}
        robot.close()  # type: ignore[no-untyped-call]
    finally:
        fusion.terminate()
        fusion.wait(10)
        router.close()  # type: ignore[no-untyped-call]


def _answers(session: zenoh.Session) -> bool:
    try:
        return "map" in health(session, timeout_s=1)
    except MapUnavailable:
        return False


def test_only_the_depth_role_changes_the_map(site: dict[str, Any]) -> None:
    robot = site["robot"]
    depth = site["session"]("depth-p0", PASSWORDS["depth-p0"])
    rogue = site["session"]("robot", PASSWORDS["robot"])  # valid credentials, wrong role
    rogue.put("depth/p9/tile", tile_payload("p9", TILE, 3.0))
    rogue.declare_queryable("map/latest", lambda q: q.reply("map/latest", b"forged"))
    time.sleep(0.5)
    depth.put("depth/p0/tile", tile_payload("p0", TILE, -1.0))
    wait_for(lambda: health(robot)["tiles_accepted"] == 1, 10, "the depth tile")
    time.sleep(0.5)
    answer = health(robot)
    assert answer["tiles_accepted"] == 1 and "p9" not in answer["pairs"]
    assert latest(robot).value_at(0.5, 0.5) < 50  # free, as depth said; the rogue's 3.0 is absent
    replies = [r.ok.payload.to_bytes() for r in robot.get("map/latest", timeout=2) if r.ok]
    assert b"forged" not in replies  # only fusion may answer map/**
    depth.close()
    rogue.close()


def test_a_pairs_depth_user_cannot_write_as_another_pair(site: dict[str, Any]) -> None:
    """One depth box's credential speaks for its own pair only: p1's cannot put p0's tiles, nor
    hold p0's liveliness token (fusion would report p0 alive, or two processes claiming it)."""
    robot = site["robot"]
    p1 = site["session"]("depth-p1", PASSWORDS["depth-p1"])
    p1.put("depth/p0/tile", tile_payload("p0", TILE, 3.0))
    token = p1.liveliness().declare_token("depth/p0/alive/forged")
    p1.put("depth/p1/tile", tile_payload("p1", Window(20, 0, 20, 20), -1.0))  # its own: allowed
    wait_for(lambda: health(robot)["tiles_accepted"] == 1, 10, "p1's own tile")
    time.sleep(0.5)
    answer = health(robot)
    assert answer["tiles_accepted"] == 1 and set(answer["pairs"]) == {"p1"}
    assert latest(robot).value_at(0.5, 0.5) == UNKNOWN  # p0's cells: never observed
    token.undeclare()
    p1.close()


@pytest.mark.parametrize("user, password", [("depth-p0", "wrong"), (None, None)])
def test_wrong_or_no_credentials_cannot_connect(
    site: dict[str, Any], user: str | None, password: str | None
) -> None:
    with pytest.raises(zenoh.ZError):
        site["session"](user, password)
