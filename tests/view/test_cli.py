"""`rigspace view`'s command line: refusals before anything is served."""

from __future__ import annotations

import socket

from rigspace.sdk.cli import main
from tests.view.conftest import BROKEN


def test_a_busy_port_is_refused_with_the_fix(capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["view", str(BROKEN), "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"Cannot serve on 127.0.0.1:{port}" in err and "another --port" in err


def test_a_port_out_of_range_and_a_missing_scene_are_refused(capsys, tmp_path):
    assert main(["view", str(BROKEN), "--port", "70000"]) == 2
    assert "--port 70000 is not a port" in capsys.readouterr().err
    assert main(["view", str(tmp_path / "nothing.usda"), "--port", "0"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_a_source_for_a_binding_the_stage_lacks_is_refused(capsys):
    from tests.view.conftest import LIVE

    assert main(["view", str(LIVE), "--port", "0", "--source", "nope=vmc://127.0.0.1:9"]) == 2
    assert "no live binding of that name" in capsys.readouterr().err
