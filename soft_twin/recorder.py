"""Recording of the node's traffic to an MCAP file in the ROS 2 bag format
(profile ``ros2``, messages CDR-encoded as on the wire, schemas as
``ros2msg`` text with their dependencies): readable by ``ros2 bag``,
Foxglove and the ``mcap`` / ``mcap-ros2-support`` Python libraries.

Every message the node publishes (its publishers are wrapped when it starts)
and every input it takes from its subscriptions (``received``) is written,
with the log time of the moment it passed through the node (increasing
through the file); a message with a header also carries its stamp as the
publish time. The ``record_file``
parameter starts a recording (a new file each time it is set), '' stops it;
the node closes it on shutdown. At the close, the counts per topic are
written as the metadata record ``soft_twin.counts``.

Crashes and long runs (issue 25): the file is written in small chunks
(:data:`CHUNK_SIZE`), each flushed to disk when complete, so a killed node
leaves a file readable up to its last complete chunk
(:mod:`soft_twin_core.files.mcap_salvage`). The ``record_max_bytes`` and
``record_max_duration_s`` parameters (0: no limit) rotate the recording:
the file is closed (complete, with its summary) and the next one opened,
named by :func:`rotated_path` (``run.mcap``, ``run_001.mcap``, ...).
"""

import importlib
import json
import os
import sys
import re
import threading
import time
from pathlib import Path

from rclpy.serialization import serialize_message

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
               "uint32", "int64", "uint64", "string", "wstring"}
_SEPARATOR = "=" * 80


def _msg_file(pkg, name):
    """The .msg definition file of pkg/msg/name: share/<pkg>/msg/ in an
    ament prefix (AMENT_PREFIX_PATH of a ROS installation, this Python's
    prefix: the venv, or the prefix the package's Python module lives in)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    try:
        mod = importlib.import_module(pkg)
        prefixes += [str(p) for p in Path(mod.__file__).resolve().parents[1:5]]
    except (ImportError, TypeError):
        pass
    for prefix in prefixes:
        f = Path(prefix) / "share" / pkg / "msg" / f"{name}.msg"
        if f.is_file():
            return f
    raise FileNotFoundError(f"no definition of {pkg}/msg/{name} in share/{pkg}/msg of {prefixes}")


def _field_types(text, pkg):
    """The complex (non-primitive) field types of a .msg text as (pkg, Type)."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2 or "=" in parts[1]:          # a constant: TYPE NAME=VALUE
            continue
        t = re.sub(r"\[.*\]$", "", parts[0])             # arrays: T[], T[3], T[<=3]
        t = re.sub(r"<=\d+$", "", t)                     # bounded strings
        if t in _PRIMITIVES:
            continue
        out.append(tuple(t.split("/", 1)) if "/" in t else (pkg, t))
    return out


def message_definition(msg_type):
    """The ``ros2msg`` schema text of a message class: its .msg text, then
    each dependency as ``MSG: pkg/Type`` after a line of 80 '=' (the
    layout of rosbag2's MCAP storage)."""
    pkg, _, name = msg_type.__module__.split(".")[0], None, msg_type.__name__
    root = (pkg, name)
    texts, order, todo = {}, [], [root]
    while todo:
        key = todo.pop(0)
        if key in texts:
            continue
        texts[key] = _msg_file(*key).read_text()
        order.append(key)
        todo += [k for k in _field_types(texts[key], key[0]) if k not in texts]
    parts = [texts[root].rstrip("\n")]
    for key in order[1:]:
        parts.append(f"{_SEPARATOR}\nMSG: {key[0]}/{key[1]}\n{texts[key].rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


def type_name(msg_type):
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def _stamp_ns(msg):
    h = getattr(msg, "header", None)
    if h is None or not hasattr(h, "stamp"):
        return None
    return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec


CHUNK_SIZE = 256 * 1024
"""Bytes of messages per MCAP chunk (before compression): a crash loses at
most the chunk being filled (:mod:`soft_twin_core.files.mcap_salvage` reads a
killed recording up to its last complete chunk). Measured on the default
twin (870 kB/s of messages, issue 25): 256 KiB is 0.3 s of its traffic and
makes the file 17 % larger than 1 MiB chunks (64 KiB: +84 %, zstd compresses
small chunks worse)."""

FLUSH_INTERVAL_S = 1.0
"""A chunk open this long (log time) is written out even if not full: a slow
recording loses at most this much on a crash."""


def rotated_path(path, index):
    """The name of file ``index`` of a rotated recording: the first (0) is
    ``path`` itself, the next ones ``<stem>_001.mcap``, ``<stem>_002.mcap``...
    (sorted by name, they are in time order)."""
    if index == 0:
        return str(path)
    root, ext = os.path.splitext(str(path))
    return f"{root}_{index:03d}{ext}"


class McapRecording:
    """One recording: an MCAP file, or a series of them when a size or
    duration limit rotates it (:func:`rotated_path`); ``write`` is
    thread-safe. Each file is complete on its own (schemas, channels,
    summary, the ``soft_twin.counts`` of its messages); the messages'
    sequence numbers run on across the files (per topic)."""

    def __init__(self, path, max_bytes=0, max_duration_s=0.0, chunk_size=CHUNK_SIZE):
        self.path = str(path)
        self.paths = []
        self.max_bytes = int(max_bytes or 0)
        self.max_duration_ns = int(1e9 * float(max_duration_s or 0.0))
        self.chunk_size = int(chunk_size)
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        self.counts = {}
        self._lock = threading.Lock()
        self._closed = False
        self._open(self.path)

    def _open(self, path):
        from mcap.writer import CompressionType, Writer
        self._fh = open(path, "wb")
        self.paths.append(path)
        self._writer = Writer(self._fh, chunk_size=self.chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="soft_twin")
        self._schemas, self._channels = {}, {}
        self._file_counts = {}
        self._file_start_ns = None
        self._written = self._fh.tell()
        self._chunk_start_ns = None

    def _finish(self):
        self._writer.add_metadata("soft_twin.counts", {k: str(v) for k, v in self._file_counts.items()})
        self._writer.finish()
        self._fh.close()

    def _channel(self, topic, msg_type):
        key = (topic, msg_type)
        ch = self._channels.get(key)
        if ch is None:
            sid = self._schemas.get(msg_type)
            if sid is None:
                sid = self._writer.register_schema(type_name(msg_type), "ros2msg",
                                                   message_definition(msg_type).encode())
                self._schemas[msg_type] = sid
            ch = self._writer.register_channel(topic, "cdr", sid)
            self._channels[key] = ch
        return ch

    def _rotate_due(self, log_ns):
        if self.max_bytes and self._fh.tell() >= self.max_bytes:
            return True
        return bool(self.max_duration_ns and self._file_start_ns is not None
                    and log_ns - self._file_start_ns >= self.max_duration_ns)

    def write(self, topic, msg):
        """Append one message; its log time is the moment it is written
        (increasing through the file), its publish time the header stamp
        (or the log time for a message without a header)."""
        data = serialize_message(msg)
        stamp = _stamp_ns(msg)
        with self._lock:
            if self._closed:
                return
            log_ns = time.time_ns()
            if self._rotate_due(log_ns):
                self._finish()
                self._open(rotated_path(self.path, len(self.paths)))
            if self._file_start_ns is None:
                self._file_start_ns = log_ns
            publish_ns = stamp or log_ns
            ch = self._channel(topic, type(msg))
            n = self.counts.get(topic, 0)
            self._writer.add_message(ch, log_time=log_ns, data=data, publish_time=publish_ns, sequence=n)
            self.counts[topic] = n + 1
            self._file_counts[topic] = self._file_counts.get(topic, 0) + 1
            if self._chunk_start_ns is None:
                self._chunk_start_ns = log_ns
            elif log_ns - self._chunk_start_ns >= 1e9 * FLUSH_INTERVAL_S and hasattr(self._writer, "flush"):
                self._writer.flush()          # (mcap 1.6, pinned) ends the chunk in progress
            pos = self._fh.tell()
            if pos != self._written:          # a chunk was written: on disk now (a crash loses at most
                self._fh.flush()              # the chunk being filled)
                self._written = pos
                self._chunk_start_ns = None

    def close(self):
        with self._lock:
            if self._closed:
                return self.counts
            self._closed = True
            self._finish()
        return self.counts


class Recorder:
    """The node's recorder: wraps its publishers, takes its inputs, follows
    the ``record_file`` parameter."""

    def __init__(self, node, publishers, state_lock=None):
        """``state_lock``: held while a state's topics are published; a
        recording starts and stops between states (all of a state's topics
        or none)."""
        self._node = node
        self._recording = None
        self._lock = threading.Lock()
        self._state_lock = state_lock if state_lock is not None else threading.Lock()
        for pub in publishers:
            self._wrap(pub)

    def _wrap(self, pub):
        publish = pub.publish
        topic = pub.topic_name

        def recorded_publish(msg):
            publish(msg)
            rec = self._recording
            if rec is not None:
                self._write(rec, topic, msg)
        pub.publish = recorded_publish

    def _write(self, rec, topic, msg):
        """Record one message; a failure stops the recording (logged), never
        the node's publishing."""
        try:
            rec.write(topic, msg)
        except Exception as e:     # noqa: BLE001 - the twin must keep running
            self._node.get_logger().error(f"recording to {rec.path} stopped: {type(e).__name__}: {e}")
            with self._lock:
                if self._recording is rec:
                    self._recording = None
            try:
                rec.close()
            except Exception:      # noqa: BLE001
                pass

    @property
    def recording(self):
        """A recording is open (every published state must be built)."""
        return self._recording is not None

    def received(self, sub, batch):
        """Inputs taken from a subscription: (msg, info) pairs."""
        rec = self._recording
        if rec is None:
            return
        for msg, _ in batch:
            self._write(rec, sub.topic_name, msg)

    def follow(self, path):
        """Start recording into ``path`` (a new file; '' stops). False if the
        file cannot be opened (logged)."""
        with self._lock:
            new = None
            if path:
                cfg = getattr(self._node, "cfg", None)
                try:
                    new = McapRecording(path, max_bytes=getattr(cfg, "record_max_bytes", 0),
                                        max_duration_s=getattr(cfg, "record_max_duration_s", 0.0))
                except OSError as e:
                    self._node.get_logger().error(f"record_file: cannot record to {path!r}: {e}")
            with self._state_lock:          # between two states
                old, self._recording = self._recording, new
            if old is not None:
                counts = old.close()
                files = f" and {len(old.paths) - 1} rotated files after it" if len(old.paths) > 1 else ""
                self._node.get_logger().info(f"recording closed: {old.path}{files} ({json.dumps(counts)})")
            if new is not None:
                self._node.get_logger().info(f"recording every published topic and input to {path}")
            return new is not None or not path

    def close(self):
        self.follow("")

    def close_now(self):
        """Close the open recording at once: the teardown watchdog's last act
        (:mod:`soft_twin.shutdown`) before it ends a process whose teardown is
        stuck. Without the state lock, which a publication stuck in the
        middleware may hold: the file gets its summary and footer (readable),
        and the state being published at that moment may lack some topics."""
        rec = self._recording
        if rec is not None:
            rec.close()
