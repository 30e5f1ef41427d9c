"""Recordings that survive a crash, and rotation (issue 25, item 5).

A killed node's MCAP file, and a clean file truncated, are read back up to
the last complete chunk with a warning (soft_twin_core.files.mcap_salvage, used by
every reader: render, view, calibrate, the articulated run reader); a size or
duration limit rotates a recording into numbered files, each complete; a
file with nothing readable still gives render's exit 2. Real rclpy
serialization, real mcap files.
"""

import os
import time
import warnings

import pytest

pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")

from geometry_msgs.msg import PoseStamped  # noqa: E402

from soft_twin import recorder  # noqa: E402
from soft_twin.recorder import McapRecording, rotated_path  # noqa: E402
from soft_twin_core.estimation import mcap_data as calibration_mcap
from soft_twin_core.estimation.calibration import CalibrationError  # noqa: E402
from soft_twin_core.files import recording  # noqa: E402
from soft_twin_core.files.mcap_salvage import TruncatedRecordingWarning, read_decoded, topic_counts  # noqa: E402

START_TIMEOUT = 120.0      # a fresh clone compiles the numba kernels first


def _pose(i):
    m = PoseStamped()
    m.header.frame_id = "base"
    m.header.stamp.sec = 1000 + i // 1000
    m.header.stamp.nanosec = (i % 1000) * 1_000_000
    m.pose.position.x = float(i)
    m.pose.position.y = 1e-3 * i ** 0.5         # not too compressible: many chunks
    return m


def _write(path, n, topics=("/t/a", "/t/b"), chunk_size=16 * 1024, **kw):
    """n messages per topic; small chunks (the node's are recorder.CHUNK_SIZE):
    many chunks in a small file."""
    rec = McapRecording(path, chunk_size=chunk_size, **kw)
    for i in range(n):
        for t in topics:
            rec.write(t, _pose(i))
    return rec.close(), rec


def _seq_by_topic(rows):
    out = {}
    for ch, msg, dec in rows:
        out.setdefault(ch.topic, []).append((msg.sequence, dec.pose.position.x))
    return out


# --- (b) a clean file truncated -------------------------------------------------

def test_truncated_file_reads_back_to_its_last_chunk(tmp_path):
    path = tmp_path / "run.mcap"
    n = 6000
    _write(path, n)
    clean = read_decoded(path)               # the complete file: no warning
    assert len(clean) == 2 * n
    assert topic_counts(path) == {"/t/a": n, "/t/b": n}          # (read, not decoded)
    data = path.read_bytes()
    cut = int(0.9 * len(data))
    path.write_bytes(data[:cut])
    with pytest.warns(TruncatedRecordingWarning) as w:
        msgs = recording.read_messages(str(path))
    text = str(w[0].message)
    assert str(path) in text and "recovered" in text and "bytes" in text and f"of {cut}" in text
    got = {t: [m.pose.position.x for m in v] for t, v in msgs.items()}
    # a prefix of each topic, in order, no gap: the messages of the complete chunks
    for t in ("/t/a", "/t/b"):
        k = len(got[t])
        assert 0.7 * n < k < n, (t, k)
        assert got[t] == [float(i) for i in range(k)]
    assert abs(len(got["/t/a"]) - len(got["/t/b"])) <= 1
    assert topic_counts(path) == {t: len(v) for t, v in got.items()}      # the same readable part
    # the calibrate MCAP loader reads it the same way
    with pytest.warns(TruncatedRecordingWarning):
        rows = calibration_mcap._iter(str(path), ["/t/a"])
    assert [r[2].pose.position.x for r in rows] == got["/t/a"]


@pytest.mark.parametrize("fraction", [0.3, 0.55, 0.75, 0.97, 0.999])
def test_any_cut_reads_a_prefix(tmp_path, fraction):
    path = tmp_path / "run.mcap"
    _write(path, 4000, topics=("/t/a",))
    data = path.read_bytes()
    path.write_bytes(data[:int(fraction * len(data))])
    with warnings.catch_warnings():
        warnings.simplefilter("error", TruncatedRecordingWarning)
        with pytest.raises(TruncatedRecordingWarning):
            read_decoded(path)
    with pytest.warns(TruncatedRecordingWarning):
        rows = read_decoded(path)
    xs = [dec.pose.position.x for _, _, dec in rows]
    assert xs == [float(i) for i in range(len(xs))] and len(xs) > 0.5 * fraction * 4000


# --- (c) rotation -----------------------------------------------------------------

def test_size_rotation_files_are_complete_and_together_hold_everything(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    path = tmp_path / "rot.mcap"
    n, limit = 8000, 60_000
    counts, rec = _write(path, n, max_bytes=limit)
    assert counts == {"/t/a": n, "/t/b": n}
    files = sorted(tmp_path.glob("rot*.mcap"))
    assert [str(f) for f in files] == rec.paths == [rotated_path(str(path), i) for i in range(len(files))]
    assert len(files) >= 4
    assert files[1].name == "rot_001.mcap"
    seen = {"/t/a": [], "/t/b": []}
    last_log = 0
    for f in files:
        assert f.stat().st_size < limit + 2 * 16 * 1024, f     # rotated at the chunk past the limit
        with open(f, "rb") as fh:                 # the seeking reader: summary and footer present
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            assert reader.get_summary() is not None
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
            per_file = {}
            for _, ch, msg, dec in reader.iter_decoded_messages(log_time_order=True):
                assert msg.log_time >= last_log
                last_log = msg.log_time
                seen[ch.topic].append((msg.sequence, dec.pose.position.x))
                per_file[ch.topic] = per_file.get(ch.topic, 0) + 1
        assert meta["soft_twin.counts"] == {k: str(v) for k, v in per_file.items()}
    for t, rows in seen.items():      # in order, no gap, no duplicate
        assert rows == [(i, float(i)) for i in range(n)], t


def test_duration_rotation(tmp_path, monkeypatch):
    clock = [1_700_000_000_000_000_000]

    def fake_ns():                 # 1 ms per message written: 4 s of recording
        clock[0] += 1_000_000
        return clock[0]
    monkeypatch.setattr(recorder.time, "time_ns", fake_ns)
    path = tmp_path / "dur.mcap"
    counts, rec = _write(path, 4000, topics=("/t/a",), max_duration_s=1.0)
    assert len(rec.paths) == 4
    xs = []
    for p in rec.paths:
        rows = read_decoded(p)
        assert (rows[-1][1].log_time - rows[0][1].log_time) < 1e9
        xs += [dec.pose.position.x for _, _, dec in rows]
    assert xs == [float(i) for i in range(4000)]


def test_a_slow_recording_is_on_disk_within_the_flush_interval(tmp_path, monkeypatch):
    """Messages that fill no chunk are written out FLUSH_INTERVAL_S after the
    chunk began: a node killed then loses at most that much."""
    clock = [1_700_000_000_000_000_000]

    def fake_ns():                 # 1 ms per message
        clock[0] += 1_000_000
        return clock[0]
    monkeypatch.setattr(recorder.time, "time_ns", fake_ns)
    path = tmp_path / "slow.mcap"
    rec = McapRecording(path)      # the node's chunk size: 2,500 messages would not fill one
    n = int(2.5 * 1000 * recorder.FLUSH_INTERVAL_S)
    for i in range(n):
        rec.write("/t/a", _pose(i))
    with pytest.warns(TruncatedRecordingWarning):     # read while open, as after a crash
        rows = read_decoded(path)
    lost = n - len(rows)           # messages of the chunk in progress: under one interval (1 ms each)
    assert 0 < lost <= 1000 * recorder.FLUSH_INTERVAL_S and len(rows) >= 2 * 1000 * recorder.FLUSH_INTERVAL_S
    rec.close()
    assert len(read_decoded(path)) == n


def test_unlimited_by_default(tmp_path):
    _, rec = _write(tmp_path / "one.mcap", 3000)
    assert rec.paths == [str(tmp_path / "one.mcap")]


@pytest.mark.parametrize("name,value,needle", [
    ("record_max_bytes", -1, "must be >= 0, got -1"),
    ("record_max_bytes", 1.5, "expected an integer"),
    ("record_max_duration_s", -2.0, "must be >= 0, got -2"),
    ("record_max_duration_s", float("nan"), "finite"),
])
def test_rotation_parameters_are_validated(name, value, needle):
    from soft_twin.config import ConfigError, validate
    with pytest.raises(ConfigError) as e:
        validate(name, value)
    assert str(e.value).startswith(name) and needle in str(e.value)
    assert validate(name, 0) == 0


# --- (d) nothing readable: still exit 2 ---------------------------------------------

def _corruptions(good):
    magic = good[:8]
    n = len(good)
    flipped = bytearray(good)
    for i in range(40, 400):                   # inside the first chunk: its CRC fails
        flipped[i] ^= 0x5A
    return {
        "empty": b"",
        "short": good[:5],
        "magic_only": magic,
        "header_cut": good[:30],
        "wrong_magic": b"\x89MCAX0\r\n" + good[8:],
        "text": b"this is not a recording\n" * 100,
        "json": b'{"time": [0, 1]}',
        "zeros": bytes(n),
        "random": os.urandom(n),
        "magic_random": magic + os.urandom(n),
        "huge_length": magic + b"\x01" + (2 ** 63).to_bytes(8, "little") + os.urandom(64),
        "first_chunk_damaged": bytes(flipped[:n // 2]),
        "first_chunk_cut": good[:200],
        "magic_twice": magic + magic,
    }


def test_files_with_nothing_readable_exit_2(tmp_path, capsys):
    from soft_twin_core import cli
    src = tmp_path / "good.mcap"
    _write(src, 3000, topics=("/soft_twin/backbone",))
    bad = _corruptions(src.read_bytes())
    assert len(bad) == 14
    for name, data in bad.items():
        p = tmp_path / f"{name}.mcap"
        p.write_bytes(data)
        code = cli.main(["render", str(p), "--robot", "tendon_arm", "--plot", str(tmp_path / "plots")])
        err = capsys.readouterr().err
        assert code == 2, (name, err)
        assert str(p) in err and "Traceback" not in err, (name, err)
        with pytest.raises(CalibrationError, match=name):
            calibration_mcap._iter(str(p), ["/soft_twin/backbone"])


# --- (a) a real node killed with SIGKILL ---------------------------------------------

@pytest.mark.ros
def test_recording_of_a_killed_node_reads_back(tmp_path, capsys):
    from soft_twin.client import NodeProcess
    from soft_twin_core import cli
    node = "salvage_twin"
    path = tmp_path / "killed.mcap"
    proc = NodeProcess(["-p", f"record_file:={path}"], node_name=node, log_path=tmp_path / "node.log")
    grown = 0
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline and proc.alive():      # until several chunks are on disk
            grown = path.stat().st_size if path.exists() else 0
            if grown > 200_000:
                break
            time.sleep(0.05)
        assert grown > 200_000, proc.output()[-3000:] if not proc.alive() else f"file at {grown} B"
    finally:
        proc.proc.kill()                    # SIGKILL: no summary, no footer
        proc.proc.wait()
        proc.stop()
    assert proc.proc.returncode == -9
    size = path.stat().st_size
    with pytest.warns(TruncatedRecordingWarning) as w:
        rows = read_decoded(path)
    assert str(path) in str(w[0].message)
    by = {}
    for ch, msg, _ in rows:
        by.setdefault(ch.topic, []).append(msg.sequence)
    ns = f"/{node}"
    states = [len(by.get(f"{ns}/{t}", [])) for t in ("backbone", "tip_pose", "strains")]
    assert min(states) >= 20 and max(states) - min(states) <= 0.1 * max(states) + 5, by.keys()
    for t, seq in by.items():                 # each topic's messages: contiguous from the start
        assert seq == list(range(len(seq))), t
    # the calibrate loader and render (exit 0, the warning on stderr naming the file)
    with pytest.warns(TruncatedRecordingWarning):
        cal = calibration_mcap._iter(str(path), [f"{ns}/strains"])
    assert len(cal) == states[2]
    code = cli.main(["render", str(path), "--robot", "tendon_arm", "--plot", str(tmp_path / "plots")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "warning" in err and str(path) in err and "recovered" in err and f"of {size}" in err
    assert any((tmp_path / "plots").iterdir())


@pytest.mark.ros
def test_node_rotates_its_recording_by_size(tmp_path):
    """record_max_bytes on a real node: numbered files, each complete, that
    together hold each topic's messages without gap or duplicate."""
    from soft_twin.client import NodeProcess
    node = "rotating_twin"
    path = tmp_path / "rot.mcap"
    proc = NodeProcess(["-p", f"record_file:={path}", "-p", "record_max_bytes:=100000"], node_name=node,
                       log_path=tmp_path / "node.log")
    third = tmp_path / "rot_002.mcap"
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline and proc.alive() and not third.exists():
            time.sleep(0.05)
        assert third.exists(), proc.output()[-3000:] if not proc.alive() else "no third file"
    finally:
        rc = proc.stop()                   # SIGINT: the last file is closed complete too
    assert rc == 0, proc.output()[-3000:]
    files = sorted(tmp_path.glob("rot*.mcap"))
    assert [f.name for f in files[:3]] == ["rot.mcap", "rot_001.mcap", "rot_002.mcap"]
    seq = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error", TruncatedRecordingWarning)      # each file complete
        for f in files:
            for ch, msg, _ in read_decoded(f):
                seq.setdefault(ch.topic, []).append(msg.sequence)
    assert f"/{node}/backbone" in seq
    for t, s in seq.items():
        assert s == list(range(len(s))), t
