"""Protocol benchmark: encode, decode, loopback transport vs plain zenoh, MCAP record.

Prints one JSON object per particle count:
{"bench": "protocol", "particles": N, "bytes": B, "encode_s", "decode_s", "transport_s",
 "raw_zenoh_s", "subscriber_decode_s", "record_s"}  (medians, seconds)

transport_s: our Publisher.put of an encoded chunk -> a subscriber in another process has
the decoded, validated Chunk (subscriber_decode_s: that decode, timed in the subscriber).
raw_zenoh_s: the same bytes through a plain zenoh put -> the subscriber holds the bytes.
Both over the same sessions (loopback TCP + shared memory), paced one message at a time,
latency from the send stamp in the payload to arrival.
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from minority.protocol import Chunk, decode_as, keys
from minority.protocol.log import LogWriter
from minority.protocol.session import LOSSLESS_QOS, NetworkOptions, Publisher, Role, open_session
from minority.protocol.wire import SENT_NS_OFFSET, stamp_sent

RUN = "bench"
RAW_KEY = "bench/raw"
SIZES = {13_000: 200, 100_000: 60, 1_000_000: 15}  # particles -> repetitions
KEYS = {"protocol": ("particles", "bytes", "encode_s", "decode_s", "transport_s", "raw_zenoh_s",
                     "subscriber_decode_s", "record_s")}


def make_chunk(n: int) -> Chunk:
    rng = np.random.default_rng(n)
    return Chunk(RUN, 20, 0.002, 0, 1, 0.005, ((0, 0, 0), (1, 1, 1)),
                 {"positions": rng.random((n, 3), dtype=np.float32),
                  "displacement_magnitude": rng.random(n, dtype=np.float32),
                  "velocity_magnitude": rng.random(n, dtype=np.float32)})


def median_time(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def subscriber(endpoint: str) -> None:
    """Child process: report one latency line per message received."""
    session = open_session(NetworkOptions(connect=[endpoint], connect_timeout_s=10), Role.CLIENT)
    out = sys.stdout

    def on_raw(sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        sent = struct.unpack_from("<q", data, SENT_NS_OFFSET)[0]
        out.write(json.dumps({"path": "raw", "latency_s": (time.time_ns() - sent) * 1e-9}) + "\n")
        out.flush()

    def on_chunk(sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        t0 = time.perf_counter()
        chunk = decode_as(data, Chunk)
        decode_s = time.perf_counter() - t0
        latency = (time.time_ns() - chunk.sent_ns) * 1e-9
        out.write(json.dumps({"path": "proto", "latency_s": latency, "decode_s": decode_s}) + "\n")
        out.flush()

    subs = [session.declare_subscriber(RAW_KEY, on_raw),
            session.declare_subscriber(keys.chunks(RUN), on_chunk)]
    out.write(json.dumps({"ready": True}) + "\n")
    out.flush()
    sys.stdin.read()  # until the parent closes our stdin
    for s in subs:
        s.undeclare()
    session.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, default=17501, help="loopback TCP port")
    parser.add_argument("--sizes", type=int, nargs="*", default=list(SIZES),
                        help="particle counts (default: 13000 100000 1000000)")
    parser.add_argument("--subscriber", metavar="ENDPOINT", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.subscriber:
        subscriber(args.subscriber)
        return

    endpoint = f"tcp/127.0.0.1:{args.port}"
    server = open_session(NetworkOptions(listen=[endpoint]), Role.SERVER)
    child = subprocess.Popen([sys.executable, "-m", "bench.protocol", "--subscriber", endpoint],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert json.loads(child.stdout.readline())["ready"]
    raw_pub = server.declare_publisher(RAW_KEY, congestion_control=LOSSLESS_QOS.congestion,
                                       priority=LOSSLESS_QOS.priority)
    chunk_pub = Publisher(server, keys.chunk(RUN, 20, 0), LOSSLESS_QOS)
    deadline = time.monotonic() + 10
    while not (chunk_pub.matched and raw_pub.matching_status.matching):
        if time.monotonic() > deadline:
            raise SystemExit("bench: the subscriber process never matched")
        time.sleep(0.01)

    def roundtrip(send) -> dict:
        send()
        return json.loads(child.stdout.readline())

    with tempfile.TemporaryDirectory() as tmp:
        log = LogWriter(Path(tmp) / "bench.mcap")
        for n in args.sizes:
            reps = SIZES.get(n, 10)
            chunk = make_chunk(n)
            payload = chunk.encode()
            frozen = bytes(payload)

            def raw_send(p=payload):
                stamp_sent(p)
                raw_pub.put(p)

            def proto_send(p=payload):
                chunk_pub.put(p)

            roundtrip(raw_send), roundtrip(proto_send)  # warm up routes and buffers
            raw, proto, sub_decode = [], [], []
            for _ in range(reps):  # interleaved so both see the same machine state
                raw.append(roundtrip(raw_send)["latency_s"])
                line = roundtrip(proto_send)
                proto.append(line["latency_s"])
                sub_decode.append(line["decode_s"])

            def record(data=frozen):
                log.write_payload(keys.chunk(RUN, 20, 0), data)
                log.flush()

            print(json.dumps({
                "bench": "protocol", "particles": n, "bytes": len(payload),
                "encode_s": round(median_time(chunk.encode, reps), 6),
                "decode_s": round(median_time(lambda d=frozen: decode_as(d, Chunk), reps), 6),
                "transport_s": round(statistics.median(proto), 6),
                "raw_zenoh_s": round(statistics.median(raw), 6),
                "subscriber_decode_s": round(statistics.median(sub_decode), 6),
                "record_s": round(median_time(record, reps), 6),
            }), flush=True)
        log.close()
    child.stdin.close()
    child.wait(timeout=30)
    server.close()


if __name__ == "__main__":
    main()
