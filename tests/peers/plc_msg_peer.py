#!/usr/bin/env python3
"""An initiating PLC on a DF1 full-duplex link: it sends MSG commands to a *target* station.

The device under test plays the S4516-DF1 role (shared/docs/df1-full-duplex-and-pccc-packets.md):
the station that a PLC-5, an SLC 5/0x or a ControlLogix ("PLC5 Typed", "SLC Typed", "PLC5 Word
Range" MSGs) reads and writes.  The serial line is a TCP socket: this script LISTENS on --port
(127.0.0.1) like a serial device server; the device under test connects to it.  Values are checked
on the target's Modbus TCP side (--modbus) through a raw-socket client.

Written from the manuals alone.  References, with the page numbers of each publication:
  [S4516]  S4516-DF1 Program Development Manual (shared/docs/df1-full-duplex-and-pccc-packets.md):
           sec. 2 (reply for every command, max 250 bytes a packet), 2.1 symbols, 2.4/2.5
           transmitter and receiver, 2.6.1 word range read/write, 2.6.2 typed logical read/write,
           4.4/5.4/6.4 (1-120 elements a MSG), App. A (STS/EXT STS), App. B (sample code: reply =
           CMD|40, DST/SRC swapped, F0/06 for an address out of range, EXT STS only when STS=F0).
  [RM]     DF1 Protocol and Command Set Reference Manual, 1770-6.5.16 (Oct. 1996):
           2-8 symbols; 4-6 transmitter flowchart (3 NAKs, 3 ENQs, retransmit same message);
           4-7 receiver; 4-10..4-17 transfer diagrams (4-13 retransmission after a lost ACK: the
           receiver discards the duplicate); 5-3/5-4 BCC and CRC; 6-7 TNS (one counter, +1 per new
           message, low byte first); 7-17 0F A2, 7-18 0F AA (234 data bytes on DF1); 7-28 0F 68;
           7-29, 7-36, 7-37 type/data parameter; 7-30 0F 67 (data type must match the file, else an
           error reply); 8-3 remote STS codes (CMD 00-08: no EXT STS); 8-4 EXT STS for CMD 0F;
           8-7..8-10 per-command error causes; 13-11/13-12 PLC-5 logical binary addressing.
  [KF2]    1770-KF2 user manual 5-10 (diagnostic loop 06 00, 243 bytes echoed), 5-51..5-53
           (typed write, type/data), 5-57 (word range read: SIZE 1 byte, up to 244 bytes; word
           range write: up to 239 bytes including the address).
  [PM020]  Logix 5000 PCCC commands, 1756-PM020F p. 89-92: 0F A1 / 0F A9 (two address fields:
           byte size, file number, file type, element number); p. 90 file type 91 = Long.
  [SLCN]   SLC 500 PCCC command notes (shared/docs/slc500-pccc-command-notes.md): 4.0 (typed write:
           data types must match), 7.3 / 4.36 masked write 0F AB (one 16-bit mask used
           repeatedly), 6.5 (50h: file does not exist), 7.7 (10h illegal command or size too large).
  [M800]   Rockwell Micro800 "DF1 full-duplex configuration" page: ACK timeout default 1 s (50 x
           20 ms), NAK retries 3, ENQ retries 3 (the same 3/3 as the [RM] 4-6 flowchart defaults).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import random
import select
import signal
import socket
import struct
import sys
import time
import traceback

DLE, STX, ETX, ENQ, ACK, NAK = 0x10, 0x02, 0x03, 0x05, 0x06, 0x15

# SLC file type codes: [RM] 7-17/7-18, [SLCN] 7.2; 0x91 Long: [PM020] p. 90 (MicroLogix/Logix only).
FILE_TYPE = {"N": 0x89, "F": 0x8A, "L": 0x91, "B": 0x85}
ELEMENT_BYTES = {"N": 2, "F": 4, "L": 4, "B": 2}
# PLC-5 type/data IDs: [RM] 7-29 (4 integer, 8 IEEE float, 9 array), size in bytes an element.
TDP_ID = {"N": (4, 2), "F": (8, 4), "L": (4, 4), "B": (4, 2)}
TDP_ARRAY = 9

# Expected error replies, (STS, EXT STS or None).  Each set cites where it comes from.
PAST_END = {(0x50, None), (0xF0, 0x06), (0xF0, 0x07), (0xF0, 0x09), (0xF0, 0x0A)}
PAST_END_WHY = ("[S4516] App. B block 2 (start address out of range: STS F0, EXT STS 06); [RM] 8-4 "
                "(06 address doesn't point to something usable, 07 file is wrong size, 09 data or file "
                "too large, 0A transaction size plus word address too large), 8-8/8-9 (F0 7: a word "
                "of the transaction does not exist; F0 9: read or write past the end of a file); "
                "[SLCN] 4.36 (50 address problem)")
NO_FILE = {(0x50, None), (0xF0, 0x06)}
NO_FILE_WHY = ("[RM] 8-7 (50: destination file does not exist), 8-8 (F0 6: DST file was not found); "
               "[SLCN] 6.5 (50h: bad address, file doesn't exist)")
TYPE_MISMATCH = {(0x10, None), (0x50, None), (0xF0, 0x06), (0xF0, 0x11), (0xF0, 0x12), (0xF0, 0x17)}
TYPE_MISMATCH_WHY = ("[RM] 7-30 (typed write: the data type must match the file, else an error reply), "
                     "8-4 (11 illegal data type, 12 invalid parameter or data, 17 type mismatch), 8-3 "
                     "(10 illegal command or format, 50 addressing problem); [SLCN] 4.0")
TOO_LARGE = {(0x10, None), (0xF0, 0x01), (0xF0, 0x09), (0xF0, 0x0A)}
TOO_LARGE_WHY = ("[RM] 8-7/8-9 (10: SIZE greater than the maximum a reply packet holds, 244), 8-4 "
                 "(01 a field has an illegal value, 09 data too large, 0A transaction size plus address "
                 "too large); [SLCN] 7.7 (10h illegal command or size too large)")
UNKNOWN_CMD = {(0x10, None)}
UNKNOWN_CMD_WHY = "[RM] 8-3 (10 illegal command or format; EXT STS only follows STS F0)"
UNKNOWN_FNC = {(0x10, None), (0xF0, 0x01), (0xF0, 0x0E)}
UNKNOWN_FNC_WHY = "[RM] 8-3 (10 illegal command or format), 8-4 (01 illegal field value, 0E command cannot be executed)"


# ----------------------------------------------------------------------------------------------
# Framing: [RM] 2-8, 5-3, 5-4; ARCHITECTURE.md (BCC = two's complement of the 8-bit sum; CRC-16
# over the message bytes plus ETX, polynomial 0xA001 reflected, initial 0, low byte first)

def bcc(msg: bytes) -> int:
    return (-sum(msg)) & 0xFF


def crc16(data: bytes) -> int:
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def check_bytes(msg: bytes, use_crc: bool) -> bytes:
    if use_crc:
        c = crc16(msg + bytes([ETX]))
        return bytes([c & 0xFF, c >> 8])
    return bytes([bcc(msg)])


def encode_frame(msg: bytes, use_crc: bool) -> bytes:
    """DLE STX, the message with every DLE doubled, DLE ETX, BCC or CRC (not DLE-doubled)."""
    return bytes([DLE, STX]) + msg.replace(bytes([DLE]), bytes([DLE, DLE])) + bytes([DLE, ETX]) \
        + check_bytes(msg, use_crc)


class Parser:
    """Bytes in, events out: ('ack',) ('nak',) ('enq',) ('frame', msg, good) ('bad', why)
    ('garbage', n).  Response symbols inside a frame are taken as embedded responses."""

    def __init__(self, use_crc: bool) -> None:
        self.use_crc = use_crc
        self.state = "idle"
        self.msg = bytearray()
        self.check = bytearray()

    def feed(self, data: bytes) -> list[tuple]:
        out: list[tuple] = []
        for b in data:
            st = self.state
            if st == "idle":
                if b == DLE:
                    self.state = "dle"
                else:
                    out.append(("garbage", 1))
            elif st == "dle":
                self.state = "idle"
                if b == STX:
                    self.msg = bytearray()
                    self.state = "body"
                elif b == ACK:
                    out.append(("ack",))
                elif b == NAK:
                    out.append(("nak",))
                elif b == ENQ:
                    out.append(("enq",))
                else:
                    out.append(("garbage", 2))
            elif st == "body":
                if b == DLE:
                    self.state = "body_dle"
                else:
                    self.msg.append(b)
                    if len(self.msg) > 600:
                        self.state = "idle"
                        out.append(("bad", "frame longer than 600 bytes"))
            elif st == "body_dle":
                if b == DLE:
                    self.msg.append(DLE)
                    self.state = "body"
                elif b == ETX:
                    self.check = bytearray()
                    self.state = "check"
                elif b in (ACK, NAK, ENQ):  # embedded response symbol ([RM] ch. 4)
                    out.append({ACK: ("ack",), NAK: ("nak",), ENQ: ("enq",)}[b])
                    self.state = "body"
                elif b == STX:
                    out.append(("bad", "DLE STX inside a frame"))
                    self.msg = bytearray()
                    self.state = "body"
                else:
                    out.append(("bad", f"DLE {b:02X} inside a frame"))
                    self.state = "idle"
            elif st == "check":
                self.check.append(b)
                if len(self.check) == (2 if self.use_crc else 1):
                    self.state = "idle"
                    msg = bytes(self.msg)
                    out.append(("frame", msg, bytes(self.check) == check_bytes(msg, self.use_crc)))
        return out


# ----------------------------------------------------------------------------------------------
# Statistics and failures

class Stats:
    def __init__(self) -> None:
        self.d: dict = {
            "msgs_sent": 0, "completed": 0, "completed_ok": 0, "error_replies": 0,
            "errors_by_sts": {}, "msg_failures": 0, "expected_errors_matched": 0,
            "expected_errors_mismatched": 0, "link_refusals_accepted": 0,
            "faults_injected": {"corrupt": 0, "lose_ack": 0, "nak_reply": 0},
            "link": collections.defaultdict(int),
            "double_applied": 0, "dup_probes": 0, "value_mismatches": 0, "late_visibility": 0,
            "checks_passed": 0, "checks_failed": 0, "failures": [], "warnings": [],
            "probes": [], "diagnostic_status": [], "rounds_done": 0, "skipped": [],
        }

    def __getitem__(self, k: str):
        return self.d[k]

    def __setitem__(self, k: str, v) -> None:
        self.d[k] = v

    def link(self, k: str, n: int = 1) -> None:
        self.d["link"][k] += n

    def write(self, path: str | None, final: bool = False) -> None:
        if not path:
            return
        out = dict(self.d)
        out["link"] = dict(self.d["link"])
        out["failures"] = self.d["failures"][:300]
        out["final"] = final
        out["ok"] = self.ok()
        tmp = path + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(out, fh, indent=1, sort_keys=True)
        os.replace(tmp, path)

    def ok(self) -> bool:
        return (self.d["checks_failed"] == 0 and self.d["msg_failures"] == 0
                and self.d["double_applied"] == 0 and self.d["value_mismatches"] == 0
                and self.d["expected_errors_mismatched"] == 0)


class LinkLost(Exception):
    pass


# ----------------------------------------------------------------------------------------------
# The DF1 full-duplex link, initiator side

class Link:
    """Transmitter per [RM] 4-6: send, wait for DLE ACK (ack timeout); DLE NAK -> retransmit the same
    frame (up to --nak-retries); timeout -> DLE ENQ (up to --enq-retries) and the receiver answers
    with its last response symbol.  Receiver per [RM] 4-7 / [S4516] 2.5: a good frame is answered
    DLE ACK, a bad one DLE NAK; a DLE ENQ from the other side is answered with our last response."""

    def __init__(self, args: argparse.Namespace, rng: random.Random, stats: Stats, log) -> None:
        self.args = args
        self.rng = rng
        self.stats = stats
        self.log = log
        self.use_crc = args.checksum == "crc"
        self.srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind((args.host, args.port))
        self.srv.listen(4)
        self.conn: socket.socket | None = None
        self.conn_rx = 0
        self.parser = Parser(self.use_crc)
        self.symbols: collections.deque = collections.deque()
        self.last_response = bytes([DLE, NAK])
        self.waiting: set[int] = set()
        self.replies: dict[int, bytes] = {}
        self.done: collections.OrderedDict[int, bytes] = collections.OrderedDict()
        self.nak_streak: dict[bytes, int] = {}
        self.connections = 0
        self.problems: list[tuple[str, str, str]] = []

    # -- connection ---------------------------------------------------------------------------
    def accept(self, timeout: float) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise SystemExit(f"no connection on {self.args.host}:{self.args.port} within {timeout} s")
            r, _, _ = select.select([self.srv], [], [], min(left, 1.0))
            if r:
                self.conn, addr = self.srv.accept()
                self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self.conn_rx = 0
                self.parser = Parser(self.use_crc)
                self.symbols.clear()
                self.connections += 1
                self.stats.link("connections")
                self.log(f"link: connection from {addr[0]}:{addr[1]}")
                return

    def send(self, data: bytes) -> None:
        assert self.conn is not None
        try:
            self.conn.sendall(data)
        except OSError as e:
            raise LinkLost(str(e)) from None
        self.stats.link("bytes_out", len(data))

    def pump(self, timeout: float) -> None:
        """Wait up to timeout for bytes and handle every event they make."""
        assert self.conn is not None
        r, _, _ = select.select([self.conn], [], [], max(timeout, 0))
        if not r:
            return
        try:
            data = self.conn.recv(4096)
        except OSError as e:
            raise LinkLost(str(e)) from None
        if not data:
            raise LinkLost("connection closed by the target")
        self.conn_rx += len(data)
        self.stats.link("bytes_in", len(data))
        if self.args.trace:
            self.log(f"  <- {data.hex(' ')}")
        for ev in self.parser.feed(data):
            self.handle(ev)

    def handle(self, ev: tuple) -> None:
        kind = ev[0]
        if kind in ("ack", "nak"):
            self.symbols.append(kind)
            self.stats.link(f"{kind}s_received")
        elif kind == "enq":
            self.stats.link("enqs_received")
            self.send(self.last_response)
        elif kind == "garbage":
            self.stats.link("garbage_bytes", ev[1])
        elif kind == "bad":
            self.stats.link("bad_frames_received")
            self.last_response = bytes([DLE, NAK])
            self.send(self.last_response)
            self.stats.link("naks_sent")
        elif kind == "frame":
            self.frame(ev[1], ev[2])

    def frame(self, msg: bytes, good: bool) -> None:
        if not good or len(msg) < 6:
            # [S4516] 2.5, [RM] 4-7: a frame with a bad BCC/CRC (or too short) is answered DLE NAK
            self.stats.link("bad_frames_received")
            self.last_response = bytes([DLE, NAK])
            self.send(self.last_response)
            self.stats.link("naks_sent")
            return
        is_reply = bool(msg[2] & 0x40)
        tns = msg[4] | (msg[5] << 8)
        awaited = is_reply and tns in self.waiting and tns not in self.replies
        if awaited and self.nak_streak.get(msg, 0) < self.args.max_nak_per_reply \
                and self.roll(self.args.nak_reply):
            # fault: NAK a good reply; the target must send it again ([RM] 4-15)
            self.nak_streak[msg] = self.nak_streak.get(msg, 0) + 1
            self.stats["faults_injected"]["nak_reply"] += 1
            self.last_response = bytes([DLE, NAK])
            self.send(self.last_response)
            self.stats.link("naks_sent")
            return
        self.last_response = bytes([DLE, ACK])
        self.send(self.last_response)
        self.stats.link("acks_sent")
        self.stats.link("frames_received")
        if not is_reply:
            self.stats.link("commands_from_target_ignored")
            return
        if awaited:
            if msg in self.nak_streak:
                self.stats.link("replies_resent_after_nak")
                del self.nak_streak[msg]
            self.replies[tns] = msg
        elif tns in self.replies or tns in self.done:
            first = self.replies.get(tns, self.done.get(tns, b""))
            self.stats.link("duplicate_replies")
            if first != msg:
                self.stats.link("duplicate_replies_differing")
                self.stats["warnings"].append(
                    f"a second reply with TNS {tns:04X} differs from the first: {first.hex(' ')} / {msg.hex(' ')}")
        else:
            self.stats.link("replies_unknown_tns")
            self.stats["failures"].append(f"reply with a TNS we have not sent or not awaiting: {msg.hex(' ')}")
            self.stats["checks_failed"] += 1

    def roll(self, p: float) -> bool:
        return p > 0 and self.rng.random() < p

    # -- transmitter --------------------------------------------------------------------------
    def corrupt(self, frame: bytes) -> bytes:
        cklen = 2 if self.use_crc else 1
        body = range(2, len(frame) - 2 - cklen)
        spots = [i for i in body if frame[i] != DLE]
        i = self.rng.choice(spots) if spots and self.rng.random() < 0.7 else len(frame) - 1
        for bit in self.rng.sample(range(8), 8):
            new = frame[i] ^ (1 << bit)
            if new != DLE:
                return frame[:i] + bytes([new]) + frame[i + 1:]
        return frame

    def send_frame(self, frame: bytes, may_corrupt: bool) -> bool:
        corrupted = False
        if may_corrupt and self.roll(self.args.corrupt):
            self.stats["faults_injected"]["corrupt"] += 1
            frame = self.corrupt(frame)
            corrupted = True
        self.stats.link("frames_sent")
        if self.args.trace:
            self.log(f"  -> {frame.hex(' ')}")
        self.send(frame)
        return corrupted

    def wait_symbol(self, deadline: float) -> str | None:
        while True:
            if self.symbols:
                return self.symbols.popleft()
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self.pump(left)

    def deliver(self, msg: bytes, faults: bool = True) -> str:
        """'ack' when the target acknowledged the frame; 'nak' when it refused it more than
        --nak-retries times; 'timeout' when --enq-retries enquiries went unanswered."""
        a = self.args
        frame = encode_frame(msg, self.use_crc)
        naks = enqs = 0
        self.symbols.clear()
        last = "corrupt" if self.send_frame(frame, faults and naks < a.nak_retries) else "frame"
        deadline = time.monotonic() + a.ack_timeout
        lost = False
        while True:
            sym = self.wait_symbol(deadline)
            if sym == "ack" and last == "corrupt":
                self.problems.append(("fail", "DLE ACK for a frame we sent with a bad BCC/CRC",
                                      "[S4516] 2.5; [RM] 4-7, 4-11"))
            if sym is None and not lost and last == "corrupt":
                self.problems.append(("warn", "no DLE NAK for a frame with a bad BCC/CRC (silence until the ACK timeout)",
                                      "[S4516] 2.5 (a bad BCC is answered with a not-acknowledge)"))
            if sym is None and not lost and last == "enq":
                self.stats.link("enqs_unanswered")
                self.problems.append(("fail", "DLE ENQ not answered with the last response symbol",
                                      "[S4516] 2.1 (ENQ requests retransmission of the response symbol); [RM] 4-12, 4-13"))
            if sym == "ack" and not lost:
                if faults and enqs < a.enq_retries and self.roll(a.lose_ack):
                    # fault: this DLE ACK "never arrived"; the ACK timer runs out ([RM] 4-12/4-13)
                    self.stats["faults_injected"]["lose_ack"] += 1
                    lost = True
                    continue
                return "ack"
            if sym == "ack" and lost:
                self.stats.link("acks_after_a_lost_ack")
                continue
            if sym == "nak":
                naks += 1
                if naks > a.nak_retries:
                    self.stats.link("gave_up_after_naks")
                    return "nak"
                self.stats.link("retransmissions_after_nak")
                lost = False
                last = "corrupt" if self.send_frame(frame, faults and naks < a.nak_retries) else "frame"
                deadline = time.monotonic() + a.ack_timeout
                continue
            # ACK timer ran out (or the ACK was dropped by the fault injector)
            enqs += 1
            if enqs > a.enq_retries:
                self.stats.link("gave_up_after_enqs")
                return "timeout"
            mode = a.lost_ack_recovery
            if lost and (mode == "resend" or (mode == "mixed" and self.rng.random() < 0.5)):
                # a transmitter that retransmits the same frame (same TNS) after a lost ACK: the target
                # must take it as a duplicate and not execute it twice ([RM] 4-13)
                self.stats.link("retransmissions_after_lost_ack")
                self.send_frame(frame, False)
                last = "frame"
            else:
                self.stats.link("enqs_sent")
                self.send(bytes([DLE, ENQ]))
                last = "enq"
            lost = False
            deadline = time.monotonic() + a.ack_timeout

    def transact(self, msg: bytes, faults: bool = True) -> tuple[bytes | None, str]:
        """Send a command, return (reply message or None, how it went)."""
        tns = msg[4] | (msg[5] << 8)
        self.waiting.add(tns)
        self.replies.pop(tns, None)
        self.done.pop(tns, None)
        try:
            how = self.deliver(msg, faults)
            if how != "ack" and tns not in self.replies:
                return None, {"nak": "the target NAKed every try ([RM] 4-6)",
                              "timeout": "no DLE ACK after the enquiries ([RM] 4-6)"}[how]
            if how != "ack":
                self.stats.link("reply_without_ack")
            deadline = time.monotonic() + self.args.reply_timeout
            while tns not in self.replies:
                left = deadline - time.monotonic()
                if left <= 0:
                    self.stats.link("reply_timeouts")
                    return None, f"no reply within {self.args.reply_timeout} s ([S4516] sec. 2: a reply for every command)"
                self.pump(left)
            return self.replies[tns], "ok"
        finally:
            self.waiting.discard(tns)
            r = self.replies.pop(tns, None)
            if r is not None:
                self.done[tns] = r
                while len(self.done) > 64:
                    self.done.popitem(last=False)

    def retransmit(self, msg: bytes, linger: float) -> str:
        """Send an already-answered message again, byte for byte (same TNS), as a link-layer
        retransmission; then keep the link serviced for `linger` seconds."""
        tns = msg[4] | (msg[5] << 8)
        how = self.deliver(msg, faults=False)
        self.settle(linger)
        if tns not in self.done:
            self.stats.link("retransmitted_tns_unknown")
        return how

    def settle(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.pump(end - time.monotonic())


# ----------------------------------------------------------------------------------------------
# Modbus TCP client on a raw socket (FC1, FC2, FC3, FC4, FC5, FC15, FC16)

class ModbusError(Exception):
    pass


class Modbus:
    def __init__(self, host: str, port: int, unit: int, timeout: float, connect_timeout: float) -> None:
        self.addr = (host, port)
        self.unit = unit
        self.timeout = timeout
        self.tid = 0
        self.sock: socket.socket | None = None
        end = time.monotonic() + connect_timeout
        while True:
            try:
                self.sock = socket.create_connection(self.addr, timeout=timeout)
                self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                return
            except OSError:
                if time.monotonic() > end:
                    raise SystemExit(f"no Modbus TCP server at {host}:{port}")
                time.sleep(0.3)

    def _recv(self, n: int) -> bytes:
        assert self.sock is not None
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ModbusError("the Modbus server closed the connection")
            buf += chunk
        return buf

    def call(self, pdu: bytes) -> bytes:
        assert self.sock is not None
        self.tid = (self.tid + 1) & 0xFFFF
        self.sock.sendall(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, self.unit) + pdu)
        try:
            while True:
                tid, proto, length, _unit = struct.unpack(">HHHB", self._recv(7))
                body = self._recv(length - 1)
                if tid == self.tid:
                    break
        except TimeoutError:
            raise ModbusError(f"no Modbus reply to function {pdu[0]} within {self.timeout} s") from None
        if proto != 0:
            raise ModbusError(f"MBAP protocol id {proto}")
        if body[0] & 0x80:
            raise ModbusError(f"Modbus exception {body[1]} to function {pdu[0]}")
        if body[0] != pdu[0]:
            raise ModbusError(f"Modbus reply function {body[0]} to request {pdu[0]}")
        return body

    def read_regs(self, fc: int, addr: int, count: int) -> list[int]:
        out: list[int] = []
        while count > 0:
            n = min(count, 125)
            body = self.call(struct.pack(">BHH", fc, addr, n))
            if body[1] != 2 * n:
                raise ModbusError(f"FC{fc} byte count {body[1]} for {n} registers")
            out += list(struct.unpack(f">{n}H", body[2:2 + 2 * n]))
            addr += n
            count -= n
        return out

    def read_bits(self, fc: int, addr: int, count: int) -> list[int]:
        out: list[int] = []
        while count > 0:
            n = min(count, 2000)
            body = self.call(struct.pack(">BHH", fc, addr, n))
            out += [(body[2 + i // 8] >> (i % 8)) & 1 for i in range(n)]
            addr += n
            count -= n
        return out

    def write_regs(self, addr: int, values: list[int]) -> None:
        while values:
            chunk, values = values[:123], values[123:]
            body = self.call(struct.pack(f">BHHB{len(chunk)}H", 16, addr, len(chunk), 2 * len(chunk), *chunk))
            if struct.unpack(">HH", body[1:5]) != (addr, len(chunk)):
                raise ModbusError("FC16 echo differs from the request")
            addr += len(chunk)

    def write_coil(self, addr: int, on: bool) -> None:
        body = self.call(struct.pack(">BHH", 5, addr, 0xFF00 if on else 0))
        if struct.unpack(">HH", body[1:5]) != (addr, 0xFF00 if on else 0):
            raise ModbusError("FC5 echo differs from the request")

    def write_coils(self, addr: int, bits: list[int]) -> None:
        packed = bytearray((len(bits) + 7) // 8)
        for i, b in enumerate(bits):
            if b:
                packed[i // 8] |= 1 << (i % 8)
        body = self.call(struct.pack(">BHHB", 15, addr, len(bits), len(packed)) + bytes(packed))
        if struct.unpack(">HH", body[1:5]) != (addr, len(bits)):
            raise ModbusError("FC15 echo differs from the request")


class MapEntry:
    """One --map item FILE:TABLE:FIRST:ELEMENTS, e.g. N7:holding:0:100."""

    def __init__(self, text: str) -> None:
        parts = text.split(":")
        if len(parts) != 4:
            raise argparse.ArgumentTypeError(f"--map item {text!r}: want FILE:TABLE:FIRST:ELEMENTS")
        name, table, first, elements = parts
        self.letter = name[0].upper()
        if self.letter not in FILE_TYPE or not name[1:].isdigit():
            raise argparse.ArgumentTypeError(f"--map item {text!r}: file must be N<n>, F<n>, L<n> or B<n>")
        self.file = int(name[1:])
        self.name = f"{self.letter}{self.file}"
        self.table = table.lower()
        if self.table not in ("holding", "input", "coil", "discrete"):
            raise argparse.ArgumentTypeError(f"--map item {text!r}: table is holding, input, coil or discrete")
        if self.table in ("coil", "discrete") and self.letter != "B":
            raise argparse.ArgumentTypeError(f"--map item {text!r}: only B files map to bits")
        self.first = int(first)
        self.elements = int(elements)
        self.regs = 2 if self.letter in "FL" else 1
        self.writable = self.table in ("holding", "coil")


class Image:
    """Reads and writes a file's elements on the Modbus side.  Values are raw unsigned integers:
    16 bits for N and B, the 32-bit pattern for F (IEEE 754) and L."""

    def __init__(self, mb: Modbus, entries: dict[str, MapEntry], word_order: str) -> None:
        self.mb = mb
        self.entries = entries
        self.high_first = word_order == "high-first"

    def read(self, e: MapEntry, elem: int, n: int) -> list[int]:
        if e.table in ("coil", "discrete"):
            bits = self.mb.read_bits(1 if e.table == "coil" else 2, e.first + 16 * elem, 16 * n)
            return [sum(bits[16 * w + b] << b for b in range(16)) for w in range(n)]
        regs = self.mb.read_regs(3 if e.table == "holding" else 4, e.first + e.regs * elem, e.regs * n)
        if e.regs == 1:
            return regs
        out = []
        for i in range(n):
            a, b = regs[2 * i], regs[2 * i + 1]
            out.append((a << 16 | b) if self.high_first else (b << 16 | a))
        return out

    def write(self, e: MapEntry, elem: int, raws: list[int]) -> None:
        if e.table == "coil":
            self.mb.write_coils(e.first + 16 * elem, [(w >> b) & 1 for w in raws for b in range(16)])
            return
        if e.regs == 1:
            self.mb.write_regs(e.first + elem, list(raws))
            return
        regs: list[int] = []
        for v in raws:
            hi, lo = v >> 16, v & 0xFFFF
            regs += [hi, lo] if self.high_first else [lo, hi]
        self.mb.write_regs(e.first + 2 * elem, regs)


# ----------------------------------------------------------------------------------------------
# PCCC encoding

def lvl(v: int, force_ff: bool = False) -> bytes:
    """One address field: a byte for 0-254, else FF + 2 bytes low first ([RM] 7-17, 13-11).  The
    [S4516] App. B sample sends the element FF-expanded even when it is small (force_ff)."""
    if v >= 255 or force_ff:
        return bytes([0xFF, v & 0xFF, (v >> 8) & 0xFF])
    return bytes([v])


PLC5_FORMS_WORD_RANGE = ["m07", "m06", "m0F", "m0Fff", "m0E"]
PLC5_FORMS_TYPED = ["m07", "m06", "m07ff"]


def plc5_address(letter: str, file: int, elem: int, form: str) -> bytes:
    """PLC-5 system address.  Logical binary ([RM] 13-11/13-12): a mask byte, bit n set = level n+1
    follows; level 1 data table (0), 2 file, 3 element, 4 sub-element.  Logical ASCII: NUL "$N7:3" NUL
    ([S4516] 2.6.1, [KF2] 5-51)."""
    if form == "ascii":
        return b"\x00$" + f"{letter}{file}:{elem}".encode() + b"\x00"
    if form == "m07":
        return b"\x07" + lvl(0) + lvl(file) + lvl(elem)
    if form == "m07ff":
        return b"\x07" + lvl(0) + lvl(file) + lvl(elem, True)
    if form == "m06":
        return b"\x06" + lvl(file) + lvl(elem)
    if form == "m0F":
        return b"\x0F" + lvl(0) + lvl(file) + lvl(elem) + lvl(0)
    if form == "m0Fff":  # the [S4516] App. B sample: mask 0F, level 1 = 0, element FF lo hi, level 4 = 0
        return b"\x0F" + lvl(0) + lvl(file) + lvl(elem, True) + lvl(0)
    if form == "m0E":
        return b"\x0E" + lvl(file) + lvl(elem) + lvl(0)
    raise ValueError(form)


def tdp_encode(type_id: int, size: int, form: str) -> bytes:
    """Type/data parameter ([RM] 7-29, 7-36): flag byte; bits 7-4 the ID (bit 7 set: bits 6-4 count
    the ID bytes that follow); bits 3-0 the size (bit 3 set: bits 2-0 count the size bytes that
    follow the ID bytes, low byte first).  Forms, all equivalent per [RM] 7-36 ("your software must
    be able to handle all three cases"): minimal; 'byte' (size in one following byte even if <= 7);
    'word' (two size bytes, as the PLC-5 example 3 on [RM] 7-37); 'padded' (an extra zero byte)."""
    if type_id <= 7:
        flag, idb = type_id << 4, b""
    else:
        flag, idb = 0x90, bytes([type_id])
    if form == "minimal":
        nsz = 0 if size <= 7 else (1 if size < 256 else 2)
    else:
        nsz = {"byte": 1, "word": 2, "padded": 3}[form]
        nsz = max(nsz, 1 if size < 256 else 2)
    if nsz == 0:
        return bytes([flag | size]) + idb
    return bytes([flag | 0x08 | nsz]) + idb + size.to_bytes(nsz, "little")


def tdp_decode(data: bytes, i: int) -> tuple[int, int, int]:
    flag = data[i]
    i += 1
    if flag & 0x80:
        n = (flag >> 4) & 7
        tid = int.from_bytes(data[i:i + n], "little")
        i += n
    else:
        tid = (flag >> 4) & 7
    if flag & 0x08:
        n = flag & 7
        size = int.from_bytes(data[i:i + n], "little")
        i += n
    else:
        size = flag & 7
    if i > len(data):
        raise ValueError("type/data parameter runs past the end of the reply")
    return tid, size, i


def element_descriptor(letter: str) -> bytes:
    tid, size = TDP_ID[letter]
    return tdp_encode(tid, size, "minimal")


def pack_raw(letter: str, raws: list[int]) -> bytes:
    return struct.pack(f"<{len(raws)}{'H' if ELEMENT_BYTES[letter] == 2 else 'I'}", *raws)


def unpack_raw(letter: str, data: bytes) -> list[int]:
    w = ELEMENT_BYTES[letter]
    return list(struct.unpack(f"<{len(data) // w}{'H' if w == 2 else 'I'}", data[:len(data) // w * w]))


def show(letter: str, raws: list[int]) -> str:
    if letter == "F":
        return "[" + ", ".join(f"{struct.unpack('<f', struct.pack('<I', r))[0]:.7g}" for r in raws) + "]"
    if letter == "L":
        return str([r - (1 << 32) if r & 0x80000000 else r for r in raws])
    if letter == "B":
        return "[" + ", ".join(f"{r:016b}" for r in raws) + "]"
    return str([r - 0x10000 if r & 0x8000 else r for r in raws])


class Reply:
    def __init__(self, msg: bytes) -> None:
        self.raw = msg
        self.dst, self.src, self.cmd, self.sts = msg[0], msg[1], msg[2], msg[3]
        self.tns = msg[4] | (msg[5] << 8)
        self.rest = msg[6:]
        self.ext = self.rest[0] if self.sts == 0xF0 and self.rest else None

    def code(self) -> str:
        if self.sts == 0xF0:
            return f"F0/{self.ext:02X}" if self.ext is not None else "F0/(missing)"
        return f"{self.sts:02X}"


# ----------------------------------------------------------------------------------------------
# The MSG script

class Failure(Exception):
    pass


class Peer:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.rng = random.Random(args.seed)
        self.stats = Stats()
        self.link = Link(args, self.rng, self.stats, self.log)
        self.tns = self.rng.randrange(0x10000) if args.tns_start is None else args.tns_start
        self.map: dict[str, MapEntry] = {}
        for item in args.map.split(","):
            e = MapEntry(item.strip())
            self.map[e.letter] = e
        self.sizes: dict[str, int] = {e.letter: e.elements for e in self.map.values()}
        for item in args.file_size or []:
            name, _, n = item.partition("=")
            letter = name[0].upper()
            if letter not in self.map or int(name[1:]) != self.map[letter].file:
                raise SystemExit(f"--file-size {item}: that file is not in --map")
            self.sizes[letter] = int(n)
        if args.no_long:
            self.map.pop("L", None)
        if "N" not in self.map:
            raise SystemExit("--map must map an N (integer) file")
        self.image: Image | None = None
        self.dup_mask: int | None = None
        self.form_i = 0
        self.step_name = ""

    # -- helpers ------------------------------------------------------------------------------
    def log(self, text: str) -> None:
        print(text, flush=True)

    def vlog(self, text: str) -> None:
        if self.args.verbose:
            self.log(text)

    def next_tns(self) -> int:
        """[RM] 6-7: one 16-bit counter, incremented for every new message."""
        self.tns = (self.tns + 1) & 0xFFFF
        return self.tns

    def fail(self, what: str, cite: str = "") -> None:
        text = f"[{self.step_name}] {what}" + (f"  (manual: {cite})" if cite else "")
        self.stats["checks_failed"] += 1
        self.stats["failures"].append(text)
        self.log("FAIL " + text)

    def link_problems(self, label: str) -> None:
        """Report what the link layer saw the target do wrong during the last MSG (once each)."""
        for kind, text, cite in dict.fromkeys(self.link.problems):
            if kind == "fail":
                self.fail(f"{label}: link: {text}", cite)
            else:
                self.warn(f"{label}: link: {text} ({cite})")
        self.link.problems.clear()

    def passed(self) -> None:
        self.stats["checks_passed"] += 1

    def warn(self, what: str) -> None:
        text = f"[{self.step_name}] {what}"
        self.stats["warnings"].append(text)
        self.log("WARN " + text)

    def pick(self, forms: list[str]) -> str:
        """Address forms in turn, so each round uses every one of them."""
        if self.args.ascii_address:
            forms = forms + ["ascii"]
        self.form_i += 1
        return forms[self.form_i % len(forms)]

    def tdp_form(self) -> str:
        f = self.args.tdp_form
        return self.rng.choice(["minimal", "byte", "word", "padded"]) if f == "mixed" else f

    def values(self, letter: str, n: int) -> list[int]:
        out = []
        for _ in range(n):
            r = self.rng.random()
            if letter in "NB":
                out.append(self.rng.choice([0x1010, 0x0210, 0x1003, 0x0000, 0xFFFF, 0x8000, 0x7FFF, 0x0510])
                           if r < 0.25 else self.rng.randrange(0x10000))
            elif letter == "L":
                out.append(self.rng.choice([0x10101010, 0x80000000, 0x7FFFFFFF, 0xFFFFFFFF, 0x00001003])
                           if r < 0.25 else self.rng.randrange(1 << 32))
            else:
                if r < 0.25:
                    f = self.rng.choice([0.0, 1.5, -2.25, 1e-3, 123456.75, 3.0e38, -1.0e-30, 2.2533e-29])
                else:
                    f = self.rng.uniform(-1e6, 1e6)
                out.append(struct.unpack("<I", struct.pack("<f", f))[0])
        return out

    # -- one MSG ------------------------------------------------------------------------------
    def msg(self, label: str, cmd: int, body: bytes, *, data_len: int | None = None,
            errors: set | None = None, why: str = "", link_refusal_ok: bool = False,
            faults: bool = True) -> tuple[Reply | None, bytes]:
        """Send one command.  data_len: bytes of data expected in a successful reply.  errors: the
        (STS, EXT STS) the manuals allow when an error reply is expected (None: success expected)."""
        a = self.args
        tns = self.next_tns()
        m = bytes([a.target_station, a.station, cmd, 0, tns & 0xFF, tns >> 8]) + body
        if len(m) > 250:
            self.vlog(f"  note: {label}: message of {len(m)} bytes, over the 250 of [S4516] sec. 2")
        self.stats["msgs_sent"] += 1
        while True:
            try:
                raw, how = self.link.transact(m, faults)
                break
            except LinkLost as e:
                probe = self.link.conn_rx == 0
                self.log(f"link: {e}; waiting for the target to connect again")
                self.link.accept(a.connect_timeout)
                if not probe:
                    self.stats["msg_failures"] += 1
                    self.fail(f"{label}: link lost during the MSG ({e})")
                    return None, m
                time.sleep(a.start_delay)
        self.link_problems(label)
        if raw is None:
            if link_refusal_ok and how.startswith("the target NAKed"):
                self.stats["link_refusals_accepted"] += 1
                self.log(f"  probe {label}: refused at the link layer (DLE NAK every try) - accepted: "
                         f"the message exceeds the 250 bytes of [S4516] sec. 2")
                self.stats["probes"].append({"probe": label, "result": "link NAK", "ok": True})
                return None, m
            self.stats["msg_failures"] += 1
            self.fail(f"{label}: MSG did not complete: {how}")
            return None, m
        r = Reply(raw)
        self.stats["completed"] += 1
        # [S4516] App. B block 2: reply CMD = command CMD | 40h, DST = our SRC, SRC = our DST
        if r.cmd != (cmd | 0x40) or r.dst != a.station or r.src != a.target_station:
            self.fail(f"{label}: reply header CMD {r.cmd:02X} DST {r.dst} SRC {r.src}, want CMD "
                      f"{cmd | 0x40:02X} DST {a.station} SRC {a.target_station}", "[S4516] App. B block 2 lines 5-7")
        if r.sts == 0:
            self.stats["completed_ok"] += 1
            if errors is not None:
                self.stats["expected_errors_mismatched"] += 1
                self.fail(f"{label}: expected an error reply, got success ({r.rest.hex(' ')})", why)
                self.stats["probes"].append({"probe": label, "result": "00", "ok": False})
            elif data_len is not None and len(r.rest) != data_len:
                self.fail(f"{label}: reply carries {len(r.rest)} data bytes, want {data_len}",
                          "[S4516] 2.6.1/2.6.2, [RM] 7-17/7-18/7-28/7-30")
            else:
                self.passed()
            return r, m
        self.stats["error_replies"] += 1
        code = r.code()
        self.stats["errors_by_sts"][code] = self.stats["errors_by_sts"].get(code, 0) + 1
        if r.sts == 0xF0 and r.ext is None:
            self.fail(f"{label}: STS F0 without an EXT STS byte", "[RM] 8-3; [S4516] App. B note")
        if r.sts != 0xF0 and r.rest:
            self.warn(f"{label}: STS {r.sts:02X} followed by {len(r.rest)} byte(s) {r.rest.hex(' ')}; "
                      "the manuals attach EXT STS only when STS = F0 ([S4516] App. B note, [RM] 8-3)")
        if errors is None:
            self.fail(f"{label}: unexpected error reply STS {code}")
            return r, m
        key = (r.sts, r.ext if r.sts == 0xF0 else None)
        ok = key in errors
        allowed = ", ".join(sorted(f"F0/{e:02X}" if s == 0xF0 else f"{s:02X}" for s, e in errors))
        self.log(f"  probe {label}: STS {r.sts:02X}" + (f" EXT STS {r.ext:02X}" if r.ext is not None else "")
                 + f" -> {'as the manual says' if ok else 'NOT what the manual says'} (allowed: {allowed})")
        self.stats["probes"].append({"probe": label, "result": code, "ok": ok, "allowed": allowed})
        if ok:
            self.stats["expected_errors_matched"] += 1
            self.passed()
        else:
            self.stats["expected_errors_mismatched"] += 1
            self.fail(f"{label}: error STS {code} is not among {allowed}", why)
        return r, m

    # -- command builders ---------------------------------------------------------------------
    def slc_body(self, fnc: int, size: int, letter: str, file: int, elem: int, three: bool,
                 ff: bool = False, ftype: int | None = None) -> bytes:
        """[RM] 7-17/7-18 (three fields), [PM020] p. 91-92 (two fields): FNC, byte size, file number,
        file type, element number[, sub-element number]."""
        t = FILE_TYPE[letter] if ftype is None else ftype
        out = bytes([fnc, size]) + lvl(file) + bytes([t]) + lvl(elem, ff)
        return out + (lvl(0) if three else b"")

    def slc_write(self, letter: str, elem: int, raws: list[int], three: bool = True, ff: bool = False,
                  file: int | None = None, **kw) -> tuple[Reply | None, bytes]:
        data = pack_raw(kw.pop("as_letter", None) or letter, raws)
        f = self.map[letter].file if file is None else file
        fnc = 0xAA if three else 0xA9
        body = self.slc_body(fnc, len(data), letter, f, elem, three, ff, kw.pop("ftype", None)) + data
        label = kw.pop("label", f"{'AA' if three else 'A9'} write {letter}{f}:{elem} x{len(raws)}")
        return self.msg(label, 0x0F, body, data_len=0, **kw)

    def slc_read(self, letter: str, elem: int, n: int, three: bool = True, ff: bool = False,
                 file: int | None = None, size: int | None = None, **kw) -> list[int] | None:
        f = self.map[letter].file if file is None else file
        nbytes = n * ELEMENT_BYTES[letter] if size is None else size
        fnc = 0xA2 if three else 0xA1
        body = self.slc_body(fnc, nbytes, letter, f, elem, three, ff, kw.pop("ftype", None))
        label = kw.pop("label", f"{'A2' if three else 'A1'} read {letter}{f}:{elem} x{n}")
        r, _ = self.msg(label, 0x0F, body, data_len=None if kw.get("errors") else nbytes, **kw)
        if r is None or r.sts != 0:
            return None
        return unpack_raw(letter, r.rest)

    def wr_write(self, elem: int, raws: list[int], file: int | None = None, packet_offset: int = 0,
                 total: int | None = None, form: str | None = None, **kw) -> tuple[Reply | None, bytes]:
        """[S4516] 2.6.1, [KF2] 5-57: FNC 00, packet offset (2), total transaction (2, words), PLC-5
        system address, data (words, low byte first)."""
        f = self.map["N"].file if file is None else file
        form = form or self.pick(PLC5_FORMS_WORD_RANGE)
        total = len(raws) if total is None else total
        body = bytes([0x00]) + struct.pack("<HH", packet_offset, total) + plc5_address("N", f, elem, form) \
            + pack_raw("N", raws)
        label = kw.pop("label", f"0F 00 word range write N{f}:{elem} x{len(raws)} off {packet_offset} ({form})")
        return self.msg(label, 0x0F, body, data_len=0, **kw)

    def wr_read(self, elem: int, n: int, file: int | None = None, size: int | None = None,
                form: str | None = None, **kw) -> list[int] | None:
        """[S4516] 2.6.1, [KF2] 5-57: FNC 01, packet offset, total transaction, address, SIZE (1 byte,
        data bytes)."""
        f = self.map["N"].file if file is None else file
        form = form or self.pick(PLC5_FORMS_WORD_RANGE)
        nbytes = 2 * n if size is None else size
        body = bytes([0x01]) + struct.pack("<HH", 0, n) + plc5_address("N", f, elem, form) + bytes([nbytes & 0xFF])
        label = kw.pop("label", f"0F 01 word range read N{f}:{elem} x{n} ({form})")
        r, _ = self.msg(label, 0x0F, body, data_len=None if kw.get("errors") else nbytes, **kw)
        if r is None or r.sts != 0:
            return None
        return unpack_raw("N", r.rest)

    def typed_write(self, letter: str, elem: int, raws: list[int], file: int | None = None,
                    as_letter: str | None = None, **kw) -> tuple[Reply | None, bytes]:
        """[RM] 7-30, [KF2] 5-51: FNC 67, packet offset, total transaction (elements), PLC-5 system
        address, type/data parameter (array of elements, [RM] 7-37 example 2), data."""
        f = self.map[letter].file if file is None else file
        dl = as_letter or letter
        form = self.pick(PLC5_FORMS_TYPED)
        data = pack_raw(dl, raws)
        desc = element_descriptor(dl)
        tdp = tdp_encode(TDP_ARRAY, len(desc) + len(data), self.tdp_form()) + desc
        body = bytes([0x67]) + struct.pack("<HH", 0, len(raws)) + plc5_address(letter, f, elem, form) + tdp + data
        label = kw.pop("label", f"0F 67 typed write {letter}{f}:{elem} x{len(raws)} ({form}, tdp {tdp.hex()})")
        return self.msg(label, 0x0F, body, data_len=0, **kw)

    def typed_read(self, letter: str, elem: int, n: int, file: int | None = None, **kw) -> list[int] | None:
        """[RM] 7-28: FNC 68, packet offset, total transaction, address, size (2 bytes, elements); the
        reply holds a type/data parameter and the data."""
        f = self.map[letter].file if file is None else file
        form = self.pick(PLC5_FORMS_TYPED)
        body = bytes([0x68]) + struct.pack("<HH", 0, n) + plc5_address(letter, f, elem, form) + struct.pack("<H", n)
        label = kw.pop("label", f"0F 68 typed read {letter}{f}:{elem} x{n} ({form})")
        r, _ = self.msg(label, 0x0F, body, **kw)
        if r is None or r.sts != 0 or kw.get("errors"):
            return None
        try:
            tid, size, i = tdp_decode(r.rest, 0)
            if tid == TDP_ARRAY:
                etid, esize, j = tdp_decode(r.rest, i)
                payload = r.rest[j:]
                if size != (j - i) + len(payload):
                    self.fail(f"{label}: array type/data size {size} but descriptor + data = {(j - i) + len(payload)} bytes",
                              "[RM] 7-37 example 2 (the size counts the descriptor and the data)")
            else:
                etid, esize, payload = tid, size, r.rest[i:]
                self.warn(f"{label}: reply type/data is not an array (ID {tid}); read as one typed value")
        except (ValueError, IndexError) as e:
            self.fail(f"{label}: cannot parse the type/data parameter of {r.rest.hex(' ')}: {e}", "[RM] 7-29, 7-36")
            return None
        want = TDP_ID[letter]
        if (etid, esize) != want:
            self.fail(f"{label}: element type ID {etid} size {esize}, want ID {want[0]} size {want[1]}", "[RM] 7-29")
            return None
        if len(payload) != n * esize:
            self.fail(f"{label}: {len(payload)} data bytes for {n} elements of {esize}", "[RM] 7-28")
            return None
        self.passed()
        return unpack_raw(letter, payload)

    def masked_write(self, elem: int, mask: int, raws: list[int], **kw) -> tuple[Reply | None, bytes]:
        """[SLCN] 7.3 / 4.36: FNC AB, byte size, file, type, element, sub-element, mask (2 bytes, low
        first, used again for every data word), data."""
        e = self.map["B"]
        data = pack_raw("B", raws)
        body = bytes([0xAB, len(data)]) + lvl(e.file) + bytes([FILE_TYPE["B"]]) + lvl(elem) + lvl(0) \
            + struct.pack("<H", mask) + data
        label = kw.pop("label", f"0F AB masked write B{e.file}:{elem} mask {mask:04X} x{len(raws)}")
        return self.msg(label, 0x0F, body, data_len=0, **kw)

    # -- value checks -------------------------------------------------------------------------
    def mb_expect(self, letter: str, elem: int, want: list[int], what: str) -> list[int] | None:
        """After a PLC write: the value is readable on Modbus at the mapped address."""
        if self.image is None:
            return None
        e = self.map[letter]
        end = time.monotonic() + self.args.settle
        polls = 0
        while True:
            got = self.image.read(e, elem, len(want))
            polls += 1
            if got == want:
                if polls > 1:
                    self.stats["late_visibility"] += 1
                self.passed()
                return got
            if time.monotonic() >= end:
                self.stats["value_mismatches"] += 1
                self.fail(f"{what}: Modbus shows {show(letter, got)} at {e.name}:{elem}, want {show(letter, want)}")
                return got
            self.link.settle(0.05)

    def plc_expect(self, reader, letter: str, want: list[int], what: str) -> list[int] | None:
        """After a Modbus write: the PLC's next read returns it (polled up to --settle)."""
        end = time.monotonic() + self.args.settle
        polls = 0
        while True:
            got = reader()
            polls += 1
            if got is None:
                return None  # the MSG failure is already counted
            if got == want:
                if polls > 1:
                    self.stats["late_visibility"] += 1
                self.passed()
                return got
            if time.monotonic() >= end:
                self.stats["value_mismatches"] += 1
                self.fail(f"{what}: the PLC read {show(letter, got)}, want {show(letter, want)}")
                return got
            self.link.settle(0.05)

    def same(self, letter: str, got: list[int] | None, want: list[int], what: str) -> None:
        if got is None:
            return
        if got == want:
            self.passed()
        else:
            self.stats["value_mismatches"] += 1
            self.fail(f"{what}: read back {show(letter, got)}, want {show(letter, want)}")

    def mb_write(self, letter: str, elem: int, raws: list[int]) -> bool:
        e = self.map[letter]
        if self.image is None or not e.writable:
            return False
        self.image.write(e, elem, raws)
        return True

    # -- the steps ----------------------------------------------------------------------------
    def regions(self) -> None:
        n = self.map["N"].elements
        if n < 10:
            raise SystemExit(f"N file of {n} elements: the script needs at least 10")
        self.rn = max(1, min(10, n // 10))
        names = ["wr", "wrmp", "tl3", "tl3ff", "tl2", "p5t", "mb", "dup", "mis"]
        self.reg_n = {k: i * self.rn for i, k in enumerate(names)}
        if "F" in self.map:
            nf = self.map["F"].elements
            self.rf = max(1, min(4, nf // 5))
            self.reg_f = {k: i * self.rf for i, k in enumerate(["tl3", "tl2", "p5t", "mb", "dup"])}
            if nf < 5:
                self.map.pop("F")
                self.stats["skipped"].append("F file has fewer than 5 elements")
        if "L" in self.map:
            nl = self.map["L"].elements
            self.rl = max(1, min(4, nl // 4))
            self.reg_l = {k: i * self.rl for i, k in enumerate(["tl3", "tl2", "mb", "dup"])}
            if nl < 4:
                self.map.pop("L")
                self.stats["skipped"].append("L file has fewer than 4 elements")
        if "B" in self.map and self.map["B"].elements < 7:
            self.map.pop("B")
            self.stats["skipped"].append("B file has fewer than 7 words")
        for k in "FLB":
            if k not in self.map and not any(s.startswith(f"{k} file") for s in self.stats["skipped"]):
                self.stats["skipped"].append(f"no {k} file in --map" + (" (--no-long)" if k == "L" and self.args.no_long else ""))

    def step_echo(self, r: int) -> None:
        """[KF2] 5-10: 06 00 sends up to 243 bytes; the reply (CMD 46) carries the same bytes."""
        sets = [bytes(range(256))[:243], bytes([DLE] * 20 + [DLE, STX, DLE, ETX, ENQ, ACK, NAK])]
        if r > 0:
            sets = [bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(1, 244)))]
        for data in sets:
            rep, _ = self.msg(f"06 00 echo {len(data)} bytes", 0x06, bytes([0x00]) + data, data_len=len(data))
            if rep is not None and rep.sts == 0:
                if rep.rest == data:
                    self.passed()
                else:
                    self.fail(f"06 00 echo: sent {data.hex(' ')}, got back {rep.rest.hex(' ')}", "[KF2] 5-10")

    def step_diag(self, r: int) -> None:
        """06 03: the reply data is device specific ([RM] ch. 10); print and keep it."""
        rep, _ = self.msg("06 03 diagnostic status", 0x06, bytes([0x03]))
        if rep is None or rep.sts != 0:
            return
        d = rep.rest
        text = "".join(chr(c) if 32 <= c < 127 else "." for c in d)
        info = {"hex": d.hex(" "), "ascii": text}
        if len(d) >= 5:
            info.update({"mode_status": f"{d[0]:02X}", "type": f"{d[1]:02X}", "ext_interface": f"{d[2]:02X}",
                         "ext_processor": f"{d[3]:02X}", "series_revision": f"{d[4]:02X}"})
        if len(d) >= 16:
            info["bulletin"] = bytes(d[5:16]).decode("ascii", "replace").strip("\x00 ")
        self.stats["diagnostic_status"].append(info)
        self.log(f"  diagnostic status ({len(d)} bytes): {d.hex(' ')}  |{text}|")
        if not d:
            self.fail("06 03 diagnostic status: reply without data", "[RM] ch. 10; 1770-HT8 B-3 (24 data bytes)")

    def step_bulk(self, r: int) -> None:
        """A transfer as large as the [S4516] App. B sample (110 elements) or the file, if smaller."""
        n = min(self.map["N"].elements, self.sizes["N"], 110)
        vals = self.values("N", n)
        how = ["AA", "00", "67"][r % 3]
        if how == "AA":
            rep, _ = self.slc_write("N", 0, vals)
        elif how == "00":
            rep, _ = self.wr_write(0, vals)
        else:
            rep, _ = self.typed_write("N", 0, vals)
        if rep is None or rep.sts != 0:
            return
        self.mb_expect("N", 0, vals, f"bulk write ({how}) of {n} elements")
        self.same("N", self.slc_read("N", 0, n), vals, "bulk read back (A2)")
        self.same("N", self.wr_read(0, n), vals, "bulk read back (0F 01)")

    def step_word_range(self, r: int) -> None:
        k, n = self.reg_n["wr"], self.rn
        vals = self.values("N", n)
        rep, _ = self.wr_write(k, vals)
        if rep is not None and rep.sts == 0:
            self.mb_expect("N", k, vals, "0F 00 word range write")
            self.same("N", self.wr_read(k, n), vals, "0F 01 word range read")
            self.same("N", self.wr_read(k, n, form="m0Fff"), vals, "0F 01 read, [S4516] App. B address form")
        # a transaction in two packets: address + packet offset ([RM] 7-28 "starting at the PLC-5
        # system address plus the packet offset"; [KF2] 5-57)
        k, n = self.reg_n["wrmp"], self.rn
        if n < 2:
            return
        vals = self.values("N", n)
        h = n // 2
        r1, _ = self.wr_write(k, vals[:h], packet_offset=0, total=n)
        r2, _ = self.wr_write(k, vals[h:], packet_offset=h, total=n)
        if r1 is not None and r2 is not None and r1.sts == 0 and r2.sts == 0:
            self.mb_expect("N", k, vals, "0F 00 two-packet transaction (packet offset)")
            self.same("N", self.wr_read(k, n), vals, "0F 01 read of the two-packet transaction")

    def step_typed_logical(self, r: int) -> None:
        for key, three, ff in (("tl3", True, False), ("tl3ff", True, True), ("tl2", False, False)):
            k, n = self.reg_n[key], self.rn
            vals = self.values("N", n)
            rep, _ = self.slc_write("N", k, vals, three=three, ff=ff)
            if rep is None or rep.sts != 0:
                continue
            tag = ("AA" if three else "A9") + (" (element FF-expanded, [S4516] App. B)" if ff else "")
            self.mb_expect("N", k, vals, f"{tag} typed logical write")
            self.same("N", self.slc_read("N", k, n, three=three, ff=ff), vals, f"{'A2' if three else 'A1'} read back")
            self.same("N", self.slc_read("N", k, n, three=not three), vals, f"{'A1' if three else 'A2'} read back")

    def step_plc5_typed(self, r: int) -> None:
        k, n = self.reg_n["p5t"], self.rn
        vals = self.values("N", n)
        rep, _ = self.typed_write("N", k, vals)
        if rep is not None and rep.sts == 0:
            self.mb_expect("N", k, vals, "0F 67 typed write")
            self.same("N", self.typed_read("N", k, n), vals, "0F 68 typed read")

    def step_floats(self, r: int) -> None:
        if "F" not in self.map:
            return
        n = self.rf
        for key, three in (("tl3", True), ("tl2", False)):
            k = self.reg_f[key]
            vals = self.values("F", n)
            rep, _ = self.slc_write("F", k, vals, three=three)
            if rep is not None and rep.sts == 0:
                self.mb_expect("F", k, vals, f"{'AA' if three else 'A9'} float write")
                self.same("F", self.slc_read("F", k, n, three=three), vals, "float typed logical read back")
        k = self.reg_f["p5t"]
        vals = self.values("F", n)
        rep, _ = self.typed_write("F", k, vals)
        if rep is not None and rep.sts == 0:
            self.mb_expect("F", k, vals, "0F 67 typed write of floats")
            self.same("F", self.typed_read("F", k, n), vals, "0F 68 typed read of floats")
            self.same("F", self.slc_read("F", k, n), vals, "A2 read of the same floats")

    def step_longs(self, r: int) -> None:
        if "L" not in self.map:
            return
        n = self.rl
        for key, three in (("tl3", True), ("tl2", False)):
            k = self.reg_l[key]
            vals = self.values("L", n)
            rep, _ = self.slc_write("L", k, vals, three=three)
            if rep is not None and rep.sts == 0:
                self.mb_expect("L", k, vals, f"{'AA' if three else 'A9'} long write (file type 91)")
                self.same("L", self.slc_read("L", k, n, three=three), vals, "long typed logical read back")

    def step_masked(self, r: int) -> None:
        if "B" not in self.map:
            return
        base = self.values("B", 3)
        rep, _ = self.slc_write("B", 0, base)
        if rep is None or rep.sts != 0:
            return
        self.mb_expect("B", 0, base, "AA write of B words")
        mask = self.rng.randrange(1, 0x10000)
        data = self.values("B", 1)
        rep, _ = self.masked_write(0, mask, data)
        want0 = (base[0] & ~mask & 0xFFFF) | (data[0] & mask)
        if rep is not None and rep.sts == 0:
            self.mb_expect("B", 0, [want0], "0F AB masked write (1 word)")
            self.same("B", self.slc_read("B", 0, 1), [want0], "A2 read after masked write")
        # two words, one mask used for both ([SLCN] 7.3 "used repeatedly")
        mask = self.rng.randrange(1, 0x10000)
        data = self.values("B", 2)
        rep, _ = self.masked_write(1, mask, data)
        want = [(base[1 + i] & ~mask & 0xFFFF) | (data[i] & mask) for i in range(2)]
        if rep is not None and rep.sts == 0:
            self.mb_expect("B", 1, want, "0F AB masked write (2 words, mask repeated)")
            self.same("B", self.slc_read("B", 1, 2), want, "A2 read after 2-word masked write")

    def step_modbus_to_plc(self, r: int) -> None:
        if self.image is None:
            return
        e = self.map["N"]
        if e.writable:
            k, n = self.reg_n["mb"], self.rn
            vals = self.values("N", n)
            self.mb_write("N", k, vals)
            self.plc_expect(lambda: self.slc_read("N", k, n), "N", vals, "Modbus FC16 -> A2 read")
            self.plc_expect(lambda: self.slc_read("N", k, n, three=False), "N", vals, "Modbus FC16 -> A1 read")
            self.plc_expect(lambda: self.wr_read(k, n), "N", vals, "Modbus FC16 -> 0F 01 read")
            self.plc_expect(lambda: self.typed_read("N", k, n), "N", vals, "Modbus FC16 -> 0F 68 read")
        if "F" in self.map and self.map["F"].writable:
            k, n = self.reg_f["mb"], self.rf
            vals = self.values("F", n)
            self.mb_write("F", k, vals)
            self.plc_expect(lambda: self.slc_read("F", k, n), "F", vals, "Modbus FC16 floats -> A2 read")
            self.plc_expect(lambda: self.typed_read("F", k, n), "F", vals, "Modbus FC16 floats -> 0F 68 read")
        if "L" in self.map and self.map["L"].writable:
            k, n = self.reg_l["mb"], self.rl
            vals = self.values("L", n)
            self.mb_write("L", k, vals)
            self.plc_expect(lambda: self.slc_read("L", k, n), "L", vals, "Modbus FC16 longs -> A2 read")
        if "B" in self.map and self.map["B"].writable:
            eb = self.map["B"]
            if eb.table == "coil":
                w = 3
                before = self.slc_read("B", w, 1)
                if before is not None:
                    bit = self.rng.randrange(16)
                    on = not ((before[0] >> bit) & 1)
                    self.image.mb.write_coil(eb.first + 16 * w + bit, on)
                    want = [(before[0] | (1 << bit)) if on else (before[0] & ~(1 << bit))]
                    self.plc_expect(lambda: self.slc_read("B", w, 1), "B", want, f"Modbus FC5 coil B{eb.file}:{w}/{bit}")
                vals = self.values("B", 2)
                self.mb_write("B", 4, vals)  # FC15
                self.plc_expect(lambda: self.slc_read("B", 4, 2), "B", vals, "Modbus FC15 coils -> A2 read")
            else:
                vals = self.values("B", 2)
                self.mb_write("B", 4, vals)
                self.plc_expect(lambda: self.slc_read("B", 4, 2), "B", vals, "Modbus FC16 B words -> A2 read")

    def dup_probe(self, label: str, letter: str, elem: int, n: int, send_a, expect_a: list[int],
                  reread) -> None:
        """Nothing applied twice ([RM] 4-13: after a lost DLE ACK the transmitter sends the same
        message again; the receiver discards the duplicate):  the PLC writes A; a Modbus client then
        writes B; the PLC's frame is sent again byte for byte (same TNS), as a link-layer
        retransmission; the value must stay B."""
        rep, m = send_a()
        if rep is None or rep.sts != 0:
            return
        if self.mb_expect(letter, elem, expect_a, f"{label}: A visible") != expect_a:
            return
        b_vals = self.values(letter, n)
        while any(((b ^ a) & 0xFFFFFFFF) == 0 for a, b in zip(expect_a, b_vals)):
            b_vals = self.values(letter, n)
        if letter == "B" and self.dup_mask is not None:
            while any(((b ^ a) & self.dup_mask) == 0 for a, b in zip(expect_a, b_vals)):
                b_vals = self.values(letter, n)
        self.mb_write(letter, elem, b_vals)
        if self.mb_expect(letter, elem, b_vals, f"{label}: B written on Modbus") != b_vals:
            return
        self.stats["dup_probes"] += 1
        how = self.link.retransmit(m, self.args.dup_wait)
        self.link_problems(label)
        if how != "ack":
            self.fail(f"{label}: the retransmitted frame was not acknowledged ({how})",
                      "[RM] 4-13 (the receiver ACKs the duplicate and discards it)")
        got_mb = self.image.read(self.map[letter], elem, n) if self.image else None
        got_plc = reread()
        applied = (got_mb is not None and got_mb != b_vals) or (got_plc is not None and got_plc != b_vals)
        if applied:
            self.stats["double_applied"] += 1
            self.fail(f"{label}: the retransmitted command was executed again: Modbus {show(letter, got_mb or [])}, "
                      f"PLC read {show(letter, got_plc or [])}, want B = {show(letter, b_vals)} (A was {show(letter, expect_a)})",
                      "[RM] 4-13 (duplicate message discarded)")
        else:
            self.passed()

    def step_dup(self, r: int) -> None:
        if self.image is None or not self.args.dup_probe or not self.map["N"].writable:
            return
        self.dup_mask = None
        k = self.reg_n["dup"]
        n = min(self.rn, 2)
        kinds = [
            ("dup 0F 00", lambda v: self.wr_write(k, v), lambda: self.wr_read(k, n)),
            ("dup 0F AA", lambda v: self.slc_write("N", k, v), lambda: self.slc_read("N", k, n)),
            ("dup 0F A9", lambda v: self.slc_write("N", k, v, three=False), lambda: self.slc_read("N", k, n)),
            ("dup 0F 67", lambda v: self.typed_write("N", k, v), lambda: self.slc_read("N", k, n)),
        ]
        for label, write, reread in kinds:
            a = self.values("N", n)
            self.dup_probe(label, "N", k, n, lambda w=write, v=a: w(v), a, reread)
        if "F" in self.map and self.map["F"].writable:
            kf = self.reg_f["dup"]
            a = self.values("F", 1)
            self.dup_probe("dup 0F AA float", "F", kf, 1, lambda: self.slc_write("F", kf, a), a,
                           lambda: self.slc_read("F", kf, 1))
        if "L" in self.map and self.map["L"].writable:
            kl = self.reg_l["dup"]
            a = self.values("L", 1)
            self.dup_probe("dup 0F AA long", "L", kl, 1, lambda: self.slc_write("L", kl, a), a,
                           lambda: self.slc_read("L", kl, 1))
        if "B" in self.map and self.map["B"].writable:
            w = 6
            before = self.slc_read("B", w, 1)
            if before is not None:
                mask = self.rng.randrange(1, 0x10000)
                data = self.values("B", 1)
                want = [(before[0] & ~mask & 0xFFFF) | (data[0] & mask)]
                self.dup_mask = mask
                self.dup_probe("dup 0F AB masked", "B", w, 1, lambda: self.masked_write(w, mask, data), want,
                               lambda: self.slc_read("B", w, 1))
                self.dup_mask = None

    def unchanged(self, letter: str, elem: int, before: list[int] | None, what: str) -> None:
        """[S4516] sec. 2: an error reply means the remote node was unable to execute the function,
        so nothing may have been written."""
        if before is None:
            return
        after = self.slc_read(letter, elem, len(before))
        mapped = elem + len(before) <= self.map[letter].elements
        mb = self.image.read(self.map[letter], elem, len(before)) if self.image and mapped else after
        if after is not None and (after != before or (mb is not None and mb != before)):
            self.fail(f"{what}: an error reply, but {letter}{self.map[letter].file}:{elem} changed from "
                      f"{show(letter, before)} to {show(letter, after)} (Modbus {show(letter, mb or [])})",
                      "[S4516] sec. 2 (error reply: the function was not executed)")
        elif after is not None:
            self.passed()

    def step_errors(self, r: int) -> None:
        a = self.args
        nN, fN = self.sizes["N"], self.map["N"].file
        # element past the end of the file
        self.slc_read("N", nN, 1, errors=PAST_END, why=PAST_END_WHY, label=f"A2 read N{fN}:{nN} (past the end)")
        self.slc_read("N", nN, 1, three=False, errors=PAST_END, why=PAST_END_WHY, label=f"A1 read N{fN}:{nN} (past the end)")
        self.slc_read("N", nN - 1, 2, errors=PAST_END, why=PAST_END_WHY, label=f"A2 read N{fN}:{nN - 1} x2 (runs past the end)")
        self.wr_read(nN, 1, errors=PAST_END, why=PAST_END_WHY, label=f"0F 01 read N{fN}:{nN} (past the end)")
        self.typed_read("N", nN, 1, errors=PAST_END, why=PAST_END_WHY, label=f"0F 68 read N{fN}:{nN} (past the end)")
        before = self.slc_read("N", nN - 1, 1)
        self.slc_write("N", nN - 1, self.values("N", 2), errors=PAST_END, why=PAST_END_WHY,
                       label=f"AA write N{fN}:{nN - 1} x2 (runs past the end)")
        self.unchanged("N", nN - 1, before, "AA write running past the end")
        before = self.slc_read("N", nN - 1, 1)
        self.wr_write(nN - 1, self.values("N", 2), errors=PAST_END, why=PAST_END_WHY,
                      label=f"0F 00 write N{fN}:{nN - 1} x2 (runs past the end)")
        self.unchanged("N", nN - 1, before, "0F 00 write running past the end")
        if "F" in self.map:
            nF = self.sizes["F"]
            self.slc_read("F", nF, 1, errors=PAST_END, why=PAST_END_WHY, label=f"A2 read F{self.map['F'].file}:{nF} (past the end)")
        # a file that does not exist
        mf = a.missing_file
        self.slc_read("N", 0, 1, file=mf, errors=NO_FILE, why=NO_FILE_WHY, label=f"A2 read N{mf}:0 (no such file)")
        self.slc_write("N", 0, [1], file=mf, errors=NO_FILE, why=NO_FILE_WHY, label=f"AA write N{mf}:0 (no such file)")
        self.wr_read(0, 1, file=mf, errors=NO_FILE, why=NO_FILE_WHY, label=f"0F 01 read N{mf}:0 (no such file)")
        self.typed_write("N", 0, [1], file=mf, errors=NO_FILE, why=NO_FILE_WHY, label=f"0F 67 write N{mf}:0 (no such file)")
        # type mismatch
        k = self.reg_n["mis"]
        before = self.slc_read("N", k, 2)
        self.slc_write("N", k, self.values("F", 1), as_letter="F", ftype=FILE_TYPE["F"], errors=TYPE_MISMATCH, why=TYPE_MISMATCH_WHY,
                       label=f"AA write float (type 8A) to N{fN}:{k} (type mismatch)")
        self.unchanged("N", k, before, "AA float to N")
        before = self.slc_read("N", k, 2)
        self.typed_write("N", k, self.values("F", 1), as_letter="F", errors=TYPE_MISMATCH, why=TYPE_MISMATCH_WHY,
                         label=f"0F 67 float type/data to N{fN}:{k} (type mismatch)")
        self.unchanged("N", k, before, "0F 67 float to N")
        if "F" in self.map:
            fF = self.map["F"].file
            self.slc_read("F", 0, 1, ftype=FILE_TYPE["N"], size=2, errors=TYPE_MISMATCH, why=TYPE_MISMATCH_WHY,
                          label=f"A2 read F{fF}:0 as integer (type 89, type mismatch)")
        # sizes over the packet limit
        big = 124  # 248 bytes: over 236 ([RM] 7-17), 240 ([S4516] 2.6.2) and the 250-byte packet
        allow = TOO_LARGE | (PAST_END if big > nN else set())
        why = TOO_LARGE_WHY + ("; the range also runs past the end: " + PAST_END_WHY if big > nN else "")
        self.slc_read("N", 0, big, errors=allow, why=why, label=f"A2 read N{fN}:0 {2 * big} bytes (over the limit)")
        self.slc_read("N", 0, big, three=False, errors=allow, why=why, label=f"A1 read N{fN}:0 {2 * big} bytes (over the limit)")
        self.typed_read("N", 0, big, errors=allow, why=why, label=f"0F 68 read N{fN}:0 x{big} (over 240 bytes)")
        w = 123  # 246 bytes: over the 244 of [KF2] 5-57 / [RM] 8-7
        allow_w = TOO_LARGE | (PAST_END if w > nN else set())
        self.wr_read(0, w, errors=allow_w, why=why, label=f"0F 01 read N{fN}:0 {2 * w} bytes (over 244)")
        nbig = 121  # 242 data bytes: over 234 ([RM] 7-18) and 240 ([S4516] 2.6.2); the frame is 254 bytes
        cur = self.slc_read("N", 0, min(nbig, nN, self.map["N"].elements, 110))
        if cur is not None:
            data = (cur + self.values("N", nbig))[:nbig]
            self.slc_write("N", 0, data, errors=TOO_LARGE | (PAST_END if nbig > nN else set()), why=why,
                           link_refusal_ok=True, label=f"AA write N{fN}:0 {2 * nbig} bytes (over the limit)")
            self.unchanged("N", 0, cur[:min(len(cur), 110)], "AA write over the size limit")
        # unknown commands
        self.msg(f"CMD {a.unknown_cmd:02X} (unknown command)", a.unknown_cmd, b"\x00\x00",
                 errors=UNKNOWN_CMD, why=UNKNOWN_CMD_WHY)
        self.msg(f"CMD 0F FNC {a.unknown_fnc:02X} (unknown function)", 0x0F, bytes([a.unknown_fnc, 0, 0]),
                 errors=UNKNOWN_FNC, why=UNKNOWN_FNC_WHY)

    # -- main loop ----------------------------------------------------------------------------
    def run(self) -> int:
        a = self.args
        self.regions()
        self.log(f"plc_msg_peer: listening on {a.host}:{a.port} (DF1 full duplex, {a.checksum.upper()}), "
                 f"DST {a.target_station}, SRC {a.station}")
        if a.modbus:
            host, _, port = a.modbus.rpartition(":")
            self.image = Image(Modbus(host or "127.0.0.1", int(port), a.unit, a.modbus_timeout, a.connect_timeout),
                               self.map, a.word_order)
        else:
            self.stats["skipped"].append("no --modbus: Modbus checks and duplicate probes skipped")
        self.link.accept(a.connect_timeout)
        time.sleep(a.start_delay)
        steps = [("echo", self.step_echo), ("diagnostic status", self.step_diag), ("bulk", self.step_bulk),
                 ("word range", self.step_word_range), ("typed logical", self.step_typed_logical),
                 ("PLC-5 typed", self.step_plc5_typed), ("floats", self.step_floats), ("longs", self.step_longs),
                 ("masked write", self.step_masked), ("Modbus -> PLC", self.step_modbus_to_plc),
                 ("nothing applied twice", self.step_dup), ("error probes", self.step_errors)]
        for rnd in range(a.rounds):
            self.log(f"=== round {rnd + 1}/{a.rounds}")
            for name, fn in steps:
                if name == "diagnostic status" and rnd > 0:
                    continue
                self.step_name = f"r{rnd + 1} {name}"
                try:
                    fn(rnd)
                except LinkLost as e:
                    self.stats["msg_failures"] += 1
                    self.fail(f"link lost: {e}")
                    self.link.accept(a.connect_timeout)
                    time.sleep(a.start_delay)
                except (ModbusError, OSError) as e:
                    self.fail(f"Modbus: {e}")
                except SystemExit:
                    raise
                except Exception:  # noqa: BLE001 - a step that crashes is a failed check; go on
                    self.fail("crashed: " + traceback.format_exc(limit=4).strip().replace("\n", " | "))
                self.stats.write(a.stats)
            self.stats["rounds_done"] = rnd + 1
        self.link.settle(0.3)
        self.stats.write(a.stats, final=True)
        s = self.stats
        self.log(f"msgs {s['msgs_sent']}, completed {s['completed']} (ok {s['completed_ok']}, errors "
                 f"{s['error_replies']} {s['errors_by_sts']}), failed MSGs {s['msg_failures']}, checks "
                 f"passed {s['checks_passed']} failed {s['checks_failed']}, double applied {s['double_applied']} "
                 f"of {s['dup_probes']} probes, value mismatches {s['value_mismatches']}, faults "
                 f"{s['faults_injected']}, link {dict(s['link'])}")
        self.log("RESULT: " + ("PASS" if s.ok() else "FAIL"))
        return 0 if s.ok() else 1


# ----------------------------------------------------------------------------------------------

EPILOG = """
--map FILE:TABLE:FIRST:ELEMENTS[,...]   (default %(map)s)
    FILE      N<n> (16-bit integer), F<n> (IEEE float), L<n> (32-bit long), B<n> (bit file)
    TABLE     holding (FC3 read / FC16 write), input (FC4, read only),
              coil (FC1 read / FC5, FC15 write), discrete (FC2, read only); bits only for B files
    FIRST     the Modbus address (0-based, as on the wire) of element 0
    ELEMENTS  elements mapped; for B files counted in 16-bit words (one coil per bit:
              coil FIRST + 16*word + bit)
    F and L elements take 2 registers each: FIRST + 2*element, in --word-order
    (high-first: the register at the lower address holds bits 31-16 of the IEEE/long value).
    The file is taken to have ELEMENTS elements on the target (past-the-end probes use element
    ELEMENTS); say --file-size N7=256 if the target's file is larger than the mapped part.

The script, each round (--rounds N, fresh random values each time, seeded by --seed):
  echo 06 00 (243 bytes incl. DLE/STX/ETX values), diagnostic status 06 03 (printed; round 1);
  a bulk transfer (110 elements as in the S4516 sample, or the file size) by 0F AA / 0F 00 / 0F 67;
  PLC-5 word range write/read 0F 00/0F 01 (five address forms, a two-packet transaction);
  SLC typed logical 0F AA/0F A2 (3 fields, also element FF-expanded as the S4516 sample) and
  0F A9/0F A1 (2 fields); PLC-5 typed 0F 67/0F 68 (type/data parameter in several equivalent forms);
  floats on F (type 8A and PLC-5 typed ID 8); longs on L (type 91; --no-long skips); masked writes
  0F AB on B (1 and 2 words); Modbus writes read back by the PLC (FC16, FC5, FC15);
  'nothing applied twice' probes; error probes (past the end, missing file, type mismatch, size over
  the limit, unknown command/function) whose STS/EXT STS must be among those the manuals allow.
After every PLC write the value must be readable on Modbus (polled up to --settle seconds).

Faults (seeded): --corrupt P damages a byte of a frame we send (the target must NAK it);
--lose-ack P drops the target's DLE ACK (we then send DLE ENQ, or retransmit the same frame with
the same TNS: --lost-ack-recovery); --nak-reply P NAKs a good reply (the target must send it again).
A fault is never injected on the last try a message has, so every failure is the target's.

Exit status 0 only when every MSG completed (or got the error reply the manuals allow) and no check
failed.  --stats FILE gets a JSON summary (rewritten after every step).
"""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    default_map = "N7:holding:0:100,F8:holding:200:20,L9:holding:300:10,B3:coil:0:16"
    ap = argparse.ArgumentParser(
        prog="plc_msg_peer.py", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="A PLC (PLC-5 / SLC 5/0x / ControlLogix MSG) initiating DF1 full-duplex commands to a "
                    "target station reached over TCP; values checked over Modbus TCP.",
        epilog=EPILOG % {"map": default_map})
    g = ap.add_argument_group("DF1 link (the target connects to us)")
    g.add_argument("--port", type=int, help="TCP port to listen on (the 'serial line'); required")
    g.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    g.add_argument("--target-station", type=int, default=1, help="DST of our commands (default 1)")
    g.add_argument("--station", type=int, default=0, help="our station, SRC of our commands (default 0)")
    g.add_argument("--checksum", choices=["crc", "bcc"], default="crc", help="CRC-16 or BCC (default crc)")
    g.add_argument("--ack-timeout", type=float, default=1.0, help="seconds to wait for DLE ACK (default 1.0)")
    g.add_argument("--nak-retries", type=int, default=3, help="retransmissions after DLE NAK (default 3)")
    g.add_argument("--enq-retries", type=int, default=3, help="DLE ENQs after ACK timeouts (default 3)")
    g.add_argument("--reply-timeout", type=float, default=5.0, help="seconds for the reply after the ACK (default 5)")
    g.add_argument("--connect-timeout", type=float, default=60.0, help="seconds to wait for the target / Modbus (default 60)")
    g.add_argument("--start-delay", type=float, default=0.5, help="seconds to wait after the target connects (default 0.5)")
    g.add_argument("--tns-start", type=lambda s: int(s, 0), default=None, help="first TNS - 1 (default: random from --seed)")
    g = ap.add_argument_group("faults (probabilities 0..1, seeded)")
    g.add_argument("--seed", type=int, default=1)
    g.add_argument("--corrupt", type=float, default=0.0, help="P(a frame we send has a damaged byte)")
    g.add_argument("--lose-ack", type=float, default=0.0, help="P(we drop the target's DLE ACK)")
    g.add_argument("--nak-reply", type=float, default=0.0, help="P(we NAK a good reply)")
    g.add_argument("--lost-ack-recovery", choices=["enq", "resend", "mixed"], default="mixed",
                   help="after a dropped ACK: DLE ENQ ([RM] 4-6), retransmit the same frame, or either (default mixed)")
    g.add_argument("--max-nak-per-reply", type=int, default=2, help="most NAKs injected on one reply (default 2)")
    g = ap.add_argument_group("Modbus TCP side")
    g.add_argument("--modbus", metavar="HOST:PORT", help="the target's Modbus TCP server (omit: no Modbus checks)")
    g.add_argument("--unit", type=int, default=1, help="Modbus unit id (default 1)")
    g.add_argument("--map", default=default_map, help="file to Modbus mapping (see below)")
    g.add_argument("--word-order", choices=["high-first", "low-first"], default="high-first",
                   help="register order of F and L elements (default high-first)")
    g.add_argument("--modbus-timeout", type=float, default=5.0)
    g.add_argument("--settle", type=float, default=1.0, help="seconds a value may take to show on the other side (default 1)")
    g = ap.add_argument_group("script")
    g.add_argument("--rounds", type=int, default=1, help="repeat the script N times with fresh values (default 1)")
    g.add_argument("--no-long", action="store_true", help="skip the L (32-bit) file")
    g.add_argument("--no-dup-probe", dest="dup_probe", action="store_false", help="skip the 'nothing applied twice' probes")
    g.add_argument("--dup-wait", type=float, default=0.5, help="seconds to service the link after a retransmission (default 0.5)")
    g.add_argument("--file-size", action="append", metavar="N7=256", help="the target's file size when larger than mapped")
    g.add_argument("--missing-file", type=int, default=99, help="a file number the target does not have (default 99)")
    g.add_argument("--unknown-cmd", type=lambda s: int(s, 0), default=0x0C, help="CMD for the unknown-command probe (default 0x0C)")
    g.add_argument("--unknown-fnc", type=lambda s: int(s, 0), default=0xFE, help="FNC under CMD 0F for the unknown-function probe (default 0xFE)")
    g.add_argument("--tdp-form", choices=["minimal", "byte", "word", "padded", "mixed"], default="mixed",
                   help="type/data parameter encoding of 0F 67 (default mixed: all [RM] 7-36 forms)")
    g.add_argument("--ascii-address", action="store_true", help="also use PLC-5 logical ASCII addresses ($N7:3)")
    g.add_argument("--stats", metavar="FILE", help="write JSON statistics here")
    g.add_argument("--verbose", action="store_true")
    g.add_argument("--trace", action="store_true", help="print every byte on the link")
    g.add_argument("--self-test", action="store_true", help="check the BCC/CRC/type-data codecs against the manuals' examples and exit")
    args = ap.parse_args(argv)
    if args.port is None and not args.self_test:
        ap.error("--port is required")
    for p in ("corrupt", "lose_ack", "nak_reply"):
        if not 0 <= getattr(args, p) <= 1:
            ap.error(f"--{p.replace('_', '-')} is a probability 0..1")
    return args


def self_test() -> int:
    # [RM] 5-4 / 5370-CVIM: data 08 09 06 00 10 04 03 -> BCC D2, frame 10 02 08 09 06 00 10 10 04 03 10 03 D2
    f = encode_frame(bytes([8, 9, 6, 0, 0x10, 4, 3]), False)
    assert f == bytes.fromhex("10020809060010100403 1003 d2".replace(" ", "")), f.hex()
    assert crc16(b"123456789") == 0xBB3D  # CRC-16/ARC check value
    p = Parser(False)
    ev = p.feed(f + bytes([DLE, ACK]))
    assert ev == [("frame", bytes([8, 9, 6, 0, 0x10, 4, 3]), True), ("ack",)], ev
    # [RM] 7-36: 43, 49 03, 4A 03 00 all mean ID 4, size 3
    for enc in (b"\x43", b"\x49\x03", b"\x4a\x03\x00"):
        assert tdp_decode(enc, 0) == (4, 3, len(enc)), enc
    # [RM] 7-37 example 2: 97 09 42 + 6 bytes; example 3: 9A 09 15 00 42
    assert tdp_encode(9, 7, "minimal") == b"\x97\x09"
    assert tdp_decode(b"\x9a\x09\x15\x00\x42", 0) == (9, 21, 4)
    for form in ("minimal", "byte", "word", "padded"):
        assert tdp_decode(tdp_encode(9, 21, form), 0)[:2] == (9, 21)
    assert element_descriptor("F") == b"\x94\x08" and element_descriptor("N") == b"\x42"
    # [RM] 13-12: N7:30 = 07 00 07 1E; B3:300 = 06 03 FF 2C 01
    assert plc5_address("N", 7, 30, "m07") == bytes.fromhex("0700071e")
    assert plc5_address("B", 3, 300, "m06") == bytes.fromhex("0603ff2c01")
    print("self-test passed")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.self_test:
        return self_test()
    try:
        peer = Peer(args)
    except (argparse.ArgumentTypeError, ValueError) as e:
        print(f"plc_msg_peer.py: error: {e}", file=sys.stderr)
        return 2

    def stop(signum, _frame):
        peer.stats["warnings"].append(f"stopped by signal {signum}")
        peer.stats.write(args.stats, final=True)
        sys.exit(2)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        return peer.run()
    except SystemExit as e:
        if isinstance(e.code, str):
            peer.stats["failures"].append(e.code)
            peer.stats["checks_failed"] += 1
            peer.stats.write(args.stats, final=True)
            print("ERROR " + e.code, file=sys.stderr)
            return 1
        raise


if __name__ == "__main__":
    sys.exit(main())
