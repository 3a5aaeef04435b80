"""The emulator's web server, out of process as a client meets it (``maniskill-irb120 emulator --rws``): sessions
lapse and are bounded (503, which abb-robot-client expects); the file service keeps $HOME, takes a chunked upload
and never maps two names onto one file; a malformed Content-Length gets RWS's error body and the server serves
on; a port out of range is one line and exit status 2; SIGTERM removes the temporary $HOME (issue 89, findings
11, 13 and 14). Each test fails on the emulator as it was before its rule."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("serial")
pytest.importorskip("lark")
requests = pytest.importorskip("requests")

from maniskill_irb120.cli import main  # noqa: E402

DIGEST = requests.auth.HTTPDigestAuth("Default User", "robotics")


def spawn(tmp: Path, *flags: str) -> tuple[subprocess.Popen, str]:
    """The emulator's CLI in its own process, its temporary files under ``tmp``; returns it and its URL."""
    env = {**os.environ, "TMPDIR": str(tmp), "PYTHONPATH": os.pathsep.join(sys.path)}
    cmd = [sys.executable, "-m", "maniskill_irb120", "emulator", "--rws", "127.0.0.1:0", *flags]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    url = proc.stdout.readline().strip()
    assert url.startswith("http://127.0.0.1:"), proc.stderr.read() if proc.poll() is not None else url
    return proc, url


def homes(tmp: Path) -> list[Path]:
    return sorted(tmp.glob("rws-home-*"))


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """One emulator for the tests that do not need their own: (URL, a logged-in requests session)."""
    tmp = tmp_path_factory.mktemp("rws")
    proc, url = spawn(tmp)
    s = requests.Session()
    s.auth = DIGEST
    yield url, s
    proc.terminate()
    proc.wait(10)


def status(resp) -> tuple[int, str]:
    body = resp.json()["_embedded"]["status"]
    assert set(body) == {"code", "msg"}
    return resp.status_code, body["msg"]


def raw_request(url: str, head: str, body: bytes = b"") -> bytes:
    """One request written by hand (what requests will not send), its whole answer."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=5) as c:
        c.sendall(head.encode() + b"\r\n" + body)
        c.shutdown(socket.SHUT_WR)
        out = b""
        while chunk := c.recv(65536):
            out += chunk
    return out


def test_sessions_are_bounded_and_lapse(tmp_path):
    """Finding 11: RobotWare keeps a bounded number of sessions and ends an idle one; the emulator kept every
    one for ever. Here 3 sessions and 2 s (RobotWare 6: 70 and an idle timeout, verify)."""
    proc, url = spawn(tmp_path, "--max-sessions", "3", "--session-idle-s", "2")
    try:
        clients = [requests.Session() for _ in range(3)]
        for c in clients:  # each logs in: a session of its own
            assert c.get(f"{url}/rw/panel/opmode?json=1", auth=DIGEST).status_code == 200
        extra = requests.get(f"{url}/rw/panel/opmode?json=1", auth=DIGEST)
        assert extra.status_code == 503
        assert "too many sessions" in status(extra)[1]
        assert clients[0].get(f"{url}/rw/panel/opmode?json=1", auth=DIGEST).status_code == 200  # still served
        time.sleep(2.3)  # all three idle past their lifetime
        assert requests.get(f"{url}/rw/panel/opmode?json=1", auth=DIGEST).status_code == 200
        stale = requests.get(f"{url}/rw/panel/opmode?json=1", cookies=clients[1].cookies)  # its cookie alone
        assert stale.status_code == 401  # the lapsed session is gone
    finally:
        proc.terminate()
        proc.wait(10)


def test_the_file_service_keeps_home_takes_chunked_bodies_and_strict_names(served):
    """Finding 13: DELETE of $HOME removed it (every later upload failed); a chunked PUT made an empty file;
    %ff and %fe were both U+FFFD, one file."""
    url, s = served
    gone = s.delete(f"{url}/fileservice/$HOME?json=1")
    assert gone.status_code == 403 and "home folder" in status(gone)[1]
    assert s.put(f"{url}/fileservice/$HOME/after.txt", b"still here").status_code in (200, 201)
    chunks = (part for part in (b"MODULE Chunked\n", b"ENDMODULE\n"))  # a generator: requests sends it chunked
    put = s.put(f"{url}/fileservice/$HOME/chunked.mod", data=chunks)
    assert put.request.headers.get("Transfer-Encoding") == "chunked"
    assert put.status_code == 201
    assert s.get(f"{url}/fileservice/$HOME/chunked.mod").content == b"MODULE Chunked\nENDMODULE\n"
    for name in ("%ff", "%fe"):
        bad = s.put(f"{url}/fileservice/$HOME/{name}", b"x")
        assert bad.status_code == 400 and "not UTF-8" in status(bad)[1]
    listing = s.get(f"{url}/fileservice/$HOME?json=1").json()["_embedded"]["_state"]
    assert sorted(i["_title"] for i in listing) == ["after.txt", "chunked.mod"]


def test_a_malformed_content_length_is_answered_and_the_server_serves_on(served):
    """Finding 14: Content-Length abc closed the connection with a traceback and no answer; a negative one held
    the handler 10 s."""
    url, s = served
    for length in ("abc", "-5"):
        t0 = time.monotonic()
        answer = raw_request(url, f"PUT /fileservice/$HOME/x.txt HTTP/1.1\r\nHost: x\r\nContent-Length: {length}\r\n")
        assert time.monotonic() - t0 < 2
        head, _, body = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 400"), answer
        assert b"is not a length in bytes" in body and b'"code": -400' in body
    assert s.get(f"{url}/rw/panel/opmode?json=1").json()["_embedded"]["_state"][0]["opmode"] == "MANR"


def test_a_port_out_of_range_is_one_line_and_status_2(capsys):
    """Finding 14: port 99999 died on an OverflowError traceback."""
    assert main(["emulator", "--rws", "127.0.0.1:99999"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0..65535" in err and "Traceback" not in err


def test_sigterm_removes_the_temporary_home(tmp_path):
    """Finding 14: SIGTERM left the temporary $HOME behind (so did this suite, which ends its emulators so)."""
    proc, url = spawn(tmp_path)
    assert len(homes(tmp_path)) == 1
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(10) == 0
    assert homes(tmp_path) == []
