#!/usr/bin/env python3
"""A packet delay line between two network interfaces, for kernels without tc netem.

Forwards every Ethernet frame that arrives on interface A out of interface B and back
the other way, each after a delay (half a round trip, plus uniform jitter) and with a
chance of loss, like `tc qdisc ... netem delay D J loss L` on both ends of a link. Meant
to run inside a middle network namespace that joins two veth pairs (scripts/netem_matrix.py
makes it): the endpoints see a real link whose packets are late, reordered by jitter and
lost, so TCP (ZeroMQ's transport) retransmits and backs off as it would on a bad network.

Frames are read with raw packet sockets and the virtio-net header (PACKET_VNET_HDR), so
segmentation-offloaded super-frames and frames whose checksum the kernel has not filled in
yet are forwarded intact: the sending kernel segments and checksums them on the way out.

    python3 scripts/packet_delay_line.py IF_A IF_B --delay-ms 50 [--jitter-ms 10] [--loss-pct 1]
Runs until SIGTERM or SIGINT; then prints one line of counts on stdout.
"""
import argparse
import heapq
import os
import random
import select
import signal
import socket
import sys
import time

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15  # linux/if_packet.h: frames carry struct virtio_net_hdr (10 bytes)
FRAME_MAX = 1 << 17   # a GSO super-frame is at most 64 KiB, plus the header


def open_port(ifname):
    """A raw packet socket bound to ifname, reading and writing frames with their vnet header."""
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    s.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    s.bind((ifname, 0))
    s.setblocking(False)
    return s


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("if_a")
    ap.add_argument("if_b")
    ap.add_argument("--delay-ms", type=float, default=0.0, help="one-way delay (ms), each direction")
    ap.add_argument("--jitter-ms", type=float, default=0.0, help="uniform jitter +- this (ms), each direction")
    ap.add_argument("--loss-pct", type=float, default=0.0, help="chance (%%) that a frame is dropped, each direction")
    ap.add_argument("--seed", type=int, default=1, help="the loss and jitter draws repeat for a seed")
    args = ap.parse_args()
    if args.delay_ms < 0 or args.jitter_ms < 0 or args.jitter_ms > args.delay_ms or not 0 <= args.loss_pct <= 100:
        sys.exit("packet_delay_line: need delay >= jitter >= 0 (ms) and loss within 0-100 %")
    # the line stands for a wire, which a busy CPU does not slow down: run it ahead of
    # ordinary processes where the system lets it (real-time FIFO; else a lower nice)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(20))
    except (AttributeError, PermissionError, OSError):
        try:
            os.nice(-10)
        except OSError:
            pass
    rng = random.Random(args.seed)
    ports = {}
    try:
        a, b = open_port(args.if_a), open_port(args.if_b)
    except OSError as e:
        sys.exit("packet_delay_line: cannot open raw sockets on %s/%s: %s" % (args.if_a, args.if_b, e))
    ports[a.fileno()] = (a, b)
    ports[b.fileno()] = (b, a)
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    queue = []  # (due time s, sequence, socket out, frame): a heap by due time
    seq = forwarded = lost = failed = 0
    delay_s, jitter_s, loss = args.delay_ms / 1000.0, args.jitter_ms / 1000.0, args.loss_pct / 100.0
    print("packet_delay_line: %s <-> %s, delay %g ms, jitter %g ms, loss %g %%" % (
        args.if_a, args.if_b, args.delay_ms, args.jitter_ms, args.loss_pct), flush=True)
    while not stop:
        # wait for a frame or for the next frame's due time, whichever comes first
        timeout = 0.05
        if queue:
            timeout = max(0.0, min(timeout, queue[0][0] - time.monotonic()))
        try:
            ready, _, _ = select.select(list(ports), [], [], timeout)
        except InterruptedError:
            continue
        now = time.monotonic()
        # take in what arrived (not our own frames going out), dropping the lost ones
        for fd in ready:
            src, dst = ports[fd]
            while True:
                try:
                    frame, addr = src.recvfrom(FRAME_MAX)
                except BlockingIOError:
                    break
                if addr[2] == socket.PACKET_OUTGOING:
                    continue
                if loss and rng.random() < loss:
                    lost += 1
                    continue
                due = now + delay_s + (rng.uniform(-jitter_s, jitter_s) if jitter_s else 0.0)
                heapq.heappush(queue, (due, seq, dst, frame))
                seq += 1
        # send out what is due
        now = time.monotonic()
        while queue and queue[0][0] <= now:
            _, _, dst, frame = heapq.heappop(queue)
            try:
                dst.send(frame)
                forwarded += 1
            except OSError:
                failed += 1  # a frame the kernel refuses (counted, like a drop on a real link)
    print("packet_delay_line: forwarded %d, lost %d, refused %d, left in flight %d" % (
        forwarded, lost, failed, len(queue)), flush=True)


if __name__ == "__main__":
    main()
