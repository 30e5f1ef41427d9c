"""Reading a recording (MCAP, ROS 2 format) that may have been cut short.

One reader for every MCAP consumer of the project (``render``, ``view``,
``calibrate``'s data files, the articulated run reader): a complete file is
read with the mcap library's seeking reader (through its summary); a file
whose end is missing or damaged (the recording process was killed, the disk
filled up, the file was truncated) is read again with the library's
streaming reader from the start, record by record, up to the last complete
chunk (chunk CRCs checked), and a :class:`TruncatedRecordingWarning` says
which file, how many messages were recovered and how many bytes at the end
could not be read. A file that is not MCAP, or holds no readable message,
is an error (the caller's error type). The command line shows the warning
as one plain line on stderr (``soft-twin-sim: warning: ...``).

No ROS import: ``mcap`` and ``mcap-ros2-support``.
"""

import os
import warnings

MAGIC = b"\x89MCAP0\r\n"


class TruncatedRecordingWarning(UserWarning):
    """A recording read only up to its last complete chunk."""


def _decoded_seeking(fh, topics):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    reader = make_reader(fh, decoder_factories=[DecoderFactory()])
    return [(channel, message, decoded) for _, channel, message, decoded
            in reader.iter_decoded_messages(topics=topics, log_time_order=True)]


def _decoded_streaming(fh, size, topics):
    """(records [(channel, message, decoded)], bytes read intact, error):
    every message up to the first record that cannot be read."""
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap_ros2.decoder import DecoderFactory
    factory = DecoderFactory()
    schemas, channels, decoders, out = {}, {}, {}, []
    keep = None if topics is None else set(topics)
    good = len(MAGIC)
    error = None
    reader = StreamReader(fh, validate_crcs=True, record_size_limit=max(size, 1))
    try:
        for rec in reader.records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                channels[rec.id] = rec
            elif isinstance(rec, Message):
                ch = channels.get(rec.channel_id)
                if ch is None or (keep is not None and ch.topic not in keep):
                    continue
                dec = decoders.get(ch.id)
                if dec is None:
                    dec = decoders[ch.id] = factory.decoder_for(ch.message_encoding, schemas.get(ch.schema_id))
                if dec is None:
                    continue
                out.append((ch, rec, dec(rec.data)))
            good = fh.tell()
    except Exception as e:        # noqa: BLE001 - the end of the readable part, whatever the library raises
        error = e
    out.sort(key=lambda r: r[1].log_time)      # stable: file order within a log time
    return out, good, error


def _open_mcap(path, error, what):
    """The file, open at its start, after checking its MCAP magic (``error``
    naming the file otherwise)."""
    try:
        fh = open(path, "rb")
    except OSError as e:
        raise error(f"cannot read the {what} {str(path)!r}: {e.strerror or e}") from None
    if fh.read(len(MAGIC)) != MAGIC:
        fh.close()
        raise error(f"{path}: not an MCAP {what} (no MCAP magic at the start of the file)")
    fh.seek(0)
    return fh


def topic_counts(path, error=ValueError, what="recording"):
    """{topic: number of messages} of an MCAP file, every message read but
    none decoded (a file cut short: its readable part; a topic without a
    message counts 0)."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader
    with _open_mcap(path, error, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        topics, counts = {}, {}
        try:
            for rec in StreamReader(fh, validate_crcs=False, record_size_limit=max(size, 1)).records:
                if isinstance(rec, Channel):
                    topics[rec.id] = rec.topic
                    counts.setdefault(rec.topic, 0)
                elif isinstance(rec, Message) and rec.channel_id in topics:
                    counts[topics[rec.channel_id]] += 1
        except Exception:          # noqa: BLE001 - the end of the readable part
            pass
        return counts


def recorded_topics(path, error=ValueError, what="recording"):
    """The set of topics of an MCAP file, none of its messages decoded."""
    return set(topic_counts(path, error, what))


def read_decoded(path, topics=None, error=ValueError, what="recording"):
    """[(channel, message, decoded message)] of an MCAP file in log-time
    order (``topics``: only these). A file cut short is read up to its last
    complete chunk, with a :class:`TruncatedRecordingWarning`; an unreadable
    file raises ``error`` with a message naming it."""
    with _open_mcap(path, error, what) as fh:
        try:
            return _decoded_seeking(fh, topics)
        except Exception as e:     # noqa: BLE001 - the mcap library raises its own error types
            first = e
        size = os.fstat(fh.fileno()).st_size
        fh.seek(0)
        out, good, err = _decoded_streaming(fh, size, topics)
    if err is None:                # streamed to the footer: the seeking reader's failure stands
        raise error(f"{path}: not a readable MCAP {what} ({type(first).__name__}: {first})") from None
    if not out:
        raise error(f"{path}: not a readable MCAP {what}: no complete message in its {size} bytes "
                    f"({type(first).__name__}: {first})") from None
    lost = size - good
    warnings.warn(f"{path}: the {what} is incomplete (cut short or damaged at byte {good} of {size}): "
                  f"recovered {len(out)} messages up to the last complete chunk; {lost} bytes "
                  f"({100.0 * lost / max(size, 1):.1f} %) at the end could not be read",
                  TruncatedRecordingWarning, stacklevel=2)
    return out


