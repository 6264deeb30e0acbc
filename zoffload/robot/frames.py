"""Camera-frame bookkeeping and the fallback state machine of the robot's camera pipeline.

Pure: no threads, no clocks, no Zenoh. Every method takes ``now`` (robot wall clock, seconds) and
the caller serialises the calls (robot/camera.py holds one lock around them), so the logic is
tested directly (tests/core/robot/test_frames.py).

Every frame the camera produced ends in exactly one bucket::

    frames_in = local_done + edge_done + dropped_* + edge_lost + edge_dropped + edge_error + error
                + pending

Fallback: when the last edge's liveliness token goes, frames in flight are booked lost at once and
every frame is detected locally. An edge frame unanswered for ``reply_timeout`` is lost; it puts
the robot in fallback too when ``fallback_losses`` frames in a row went unanswered and nothing came
back for a whole timeout (a frame lost now and then is the link's loss: counted, and seen by the
strategy). In fallback one probe frame goes to the edge every ``probe_period`` while an edge is
present; ``resume_after`` prompt answers in a row end the fallback (hysteresis).

Copies: a strategy may have a frame detected locally *and* sent to the edge only to measure the edge
(``both``). The frame's bucket is its local result; the copy's answer, loss or replacement is an
observation for the strategy and a counter (``copies_*``), never a second bucket.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from zoffload.policy.offload import BOTH, EDGE, HOLD, LOCAL, NAN, SKIP, EdgeReply, OffloadState, Strategy
from zoffload.robot.encoding import RAW, EncodingChoice
from zoffload.robot.framelog import FRAME_FIELDS, FrameLog
from zoffload.robot.linkclock import LinkClock

__all__ = ["DONE", "DROPPED", "FRAME_FIELDS", "FallbackRules", "FrameBook", "RobotView"]

log = logging.getLogger("zoffload.robot.frames")

MAX_FALLBACK_EVENTS = 1000  # fallbacks listed in the summary (all are counted)
# Final buckets of a camera frame (skipped: no side could finish it while fresh)
DONE = ("local_done", "edge_done")
DROPPED = ("dropped_camera", "dropped_unreadable", "dropped_stale", "dropped_window", "dropped_send",
           "skipped", "edge_lost", "edge_dropped", "edge_error", "error")


@dataclass(frozen=True)
class RobotView:
    """What the camera pipeline knows of the robot side when a frame arrives."""

    cpu_percent: float = NAN  # process CPU, smoothed (one core = 100)
    mbps_out: float = NAN
    local_busy: bool = False  # the local detector is on a frame
    local_busy_for: float = 0.0  # seconds it has spent on it
    local_waiting: bool = False  # a frame waits in its slot
    local_last_start: float = -math.inf
    send_waiting: bool = False  # a frame waits in the sender's slot
    cpu_time: float = NAN  # process CPU seconds so far
    local_cpu_time: float = NAN  # of which the local detector's
    cpu_quota: float = NAN  # cores (a CFS quota in force), NaN: none


@dataclass(frozen=True)
class FallbackRules:
    reply_timeout: float = 0.5  # an edge frame unanswered this long is lost
    fallback_losses: int = 3  # lost in a row (and a silent edge) → fallback
    probe_period: float = 0.5  # in fallback: one frame to the edge this often
    resume_after: int = 3  # prompt probe answers in a row that end the fallback


class FrameBook:
    """``keep``: finished records held in memory (None: all of them), older ones retire to
    ``folder`` (robot/framelog.py)."""

    def __init__(self, strategy: Strategy, rules: FallbackRules, keep: int | None = None,
                 folder: Path | None = None, encodings: EncodingChoice | None = None) -> None:
        self.strategy = strategy
        self.rules = rules
        self.encodings = encodings if encodings is not None else EncodingChoice(RAW)
        self.counters: Counter[str] = Counter()
        self.log = FrameLog(keep, folder)
        self.records = self.log.records  # seq -> record (the newest ones)
        self.persons = self.log.persons  # seq -> person boxes and scores (of those records)
        self.per_edge: Counter[str] = Counter()  # frames each edge detected
        self.in_flight: dict[int, float] = {}  # seq -> send time
        self.copies: dict[int, float] = {}  # seq -> send time of a copy (the frame is detected locally)
        self.fallback = False
        self.fallback_events: list[dict[str, float]] = []
        self.edge_present = False
        self._probe_streak = 0
        self._last_probe = -float("inf")
        self._last_reply = -float("inf")
        self._last_loss = -math.inf  # an edge frame or copy booked lost (it may still be on the link)
        self._lost_streak = 0
        self._last_answer = -math.inf  # the edge's last answer to a frame or copy in flight
        self._last_arrival = -math.inf  # when that frame reached the edge
        self.link_clock = LinkClock()  # the link's time per frame from the edge's arrival stamps
        self._puts = 0  # frames and copies put so far (their order on the link)
        self._stamped: bool | None = None  # whether the last answer carried the edge's arrival

    # Frames in, decisions out
    def camera_dropped(self, n: int, unreadable: int = 0) -> None:
        """Frames the camera replaced before the loop took them, and frames its source could not
        read (skipped by the sensor thread: their seqs are gaps)."""
        self.counters["frames_in"] += n + unreadable
        self.counters["dropped_camera"] += n
        self.counters["dropped_unreadable"] += unreadable

    def decide(self, seq: int, index: int, capture: float, now: float,
               robot: RobotView | None = None) -> tuple[str, bool]:
        """Book a new frame and choose its side: ``local``, ``edge``, ``both`` (local, plus a copy to
        the edge), ``hold`` or ``skip``; the second value says whether it is a fallback probe. A
        held or skipped frame is finished here (``dropped_window``, ``skipped``)."""
        r = robot or RobotView()
        self.records[seq] = {"seq": seq, "index": index, "capture": capture, "status": "pending"}
        self.log.trim(held=self.copies)  # records grow only here: the bound is kept here
        self.counters["frames_in"] += 1
        probe = (self.fallback and self.edge_present and not self.in_flight
                 and now - self._last_probe >= self.rules.probe_period and self.strategy.name != "robot")
        if probe:
            self._last_probe = now
            side = EDGE
        else:
            oldest = min(self.in_flight.values(), default=now)
            sends = sorted([*self.in_flight.items(), *self.copies.items()], key=lambda kv: kv[1])
            side = self.strategy.decide(OffloadState(
                now=now, edge_available=self.edge_present and not self.fallback, cpu_percent=r.cpu_percent,
                mbps_out=r.mbps_out, oldest_in_flight_age=now - oldest, in_flight=len(self.in_flight),
                local_busy=r.local_busy, capture=capture, local_busy_for=r.local_busy_for,
                local_waiting=r.local_waiting, local_last_start=r.local_last_start,
                send_waiting=r.send_waiting,
                edge_sends=tuple((t, float(self.records[k].get("bytes", NAN))) for k, t in sends),
                cpu_time=r.cpu_time, local_cpu_time=r.local_cpu_time, cpu_quota=r.cpu_quota))
        self.records[seq]["side"] = LOCAL if side == BOTH else side
        estimates = getattr(self.strategy, "estimates", None)
        if estimates is not None and not probe:  # the strategy's expected finish, ms after capture
            self.records[seq].update(est_local_ms=(estimates[0] - capture) * 1e3,
                                     est_edge_ms=(estimates[1] - capture) * 1e3)
        if side == HOLD:  # the edge's window is full and local is slower: hold this one back
            self.finish(seq, "dropped_window")
        elif side == SKIP:  # no side would finish it while it is fresh
            self.finish(seq, "skipped")
        return side, probe

    def sent(self, seq: int, now: float, probe: bool, copy: bool = False, edge: str = "") -> None:
        """The frame (or its copy) is handed to the sender: in flight, its timeout runs from now on.
        ``edge``: the edge asked to detect it ("" = any edge that hears it); only its answer counts."""
        # Nothing ahead of it on the link or at the edge: its answer time is the path's base. Not
        # after a loss until an answer came: a frame booked lost may still be in the sender or on
        # the link
        alone = not self.in_flight and not self.copies and self._last_loss <= self._last_reply
        self.records[seq].update(edge=edge, alone=int(alone))
        if copy:
            self.records[seq].update(copy=1)
            self.copies[seq] = now
            return
        self.records[seq].update(send=now, probe=int(probe))
        self.in_flight[seq] = now

    def putting(self, seq: int, now: float, mono: float | None = None, **fields: Any) -> None:
        """The sender puts the frame (or copy) now: stamped with the time (``put``; ``mono`` the
        monotonic clock's, for robot/linkclock.py, default ``now``) and its place in the link's order
        (``put_n``), with the sender's ``fields`` (bytes, encode_ms, sent_size)."""
        self._puts += 1
        rec = self.records.get(seq)
        if rec is not None:
            rec.update(fields, put=now, put_mono=now if mono is None else mono, put_n=self._puts)

    def encoding_for(self, seq: int, now: float) -> tuple[str, bool]:
        """The encoding the sender gives this frame (or copy) now (robot/encoding.py), recorded."""
        encoding, trial = self.encodings.pick(now)
        self.records[seq].update(encoding=encoding, trial=int(trial))
        self.counters[f"sent_{encoding}"] += 1
        return encoding, trial

    def _encoding_lost(self, rec: dict[str, Any], now: float) -> None:
        if rec.get("encoding") and self.encodings.lost(rec["encoding"], bool(rec.get("trial")), now):
            self._encoding_switched()

    def _encoding_switched(self) -> None:
        self.strategy.on_encoding_change()
        _, to, why = self.encodings.events[-1]
        log.info("frames to the edge now %s: %s", "raw" if to == RAW else "JPEG", why)

    def edge_of(self, seq: int) -> str:
        """The edge a frame waiting to be sent goes to."""
        return str(self.records[seq].get("edge", ""))

    def send_replaced(self, seq: int) -> None:
        """A frame (or copy) still waiting for the link when a newer one took its place. A frame
        booked meanwhile (lost when its edge went, or overdue while the link was blocked) keeps
        that bucket."""
        if self.copies.pop(seq, None) is not None:
            self.counters["copies_replaced"] += 1
            return
        if self.in_flight.pop(seq, None) is not None:
            self.finish(seq, "dropped_send")

    def send_failed(self, seq: int, now: float) -> None:
        """The frame could not be encoded for the link (a copy's frame is still detected locally;
        a frame booked meanwhile keeps its bucket). A trial of raw frames that failed so is over
        (a failed encoding says nothing of the link otherwise)."""
        rec = self.records.get(seq)
        if rec is not None and rec.get("trial") and self.waiting_to_send(seq):
            self._encoding_lost(rec, now)
        if self.copies.pop(seq, None) is not None:
            self.counters["copies_failed"] += 1
            return
        if seq in self.in_flight:
            self.failed(seq)

    def waiting_to_send(self, seq: int) -> bool:
        """Whether the sender should still put this frame (or copy): not booked meanwhile."""
        return seq in self.in_flight or seq in self.copies

    def local_replaced(self, seq: int) -> None:
        """A frame still waiting for the local detector when a newer one took its place."""
        self.finish(seq, "dropped_stale")

    def failed(self, seq: int) -> None:
        """The frame could not be encoded or detected (a bad frame is counted, the run goes on)."""
        self.in_flight.pop(seq, None)
        self.finish(seq, "error")

    def finish(self, seq: int, bucket: str) -> None:
        """Book the frame in its one bucket. A frame already booked stays where it is (counted as
        ``rebooked``, logged: every path that can reach a booked frame checks first)."""
        rec = self.records[seq]
        if rec["status"] != "pending":
            self.counters["rebooked"] += 1
            log.warning("frame %d: already %s, not booked again as %s", seq, rec["status"], bucket)
            return
        rec["status"] = bucket
        self.counters[bucket] += 1

    # Results
    def local_result(self, seq: int, now: float, service: float, infer_time: float,
                     boxes: np.ndarray, scores: np.ndarray, cpu: float | None = None) -> None:
        rec = self.records.get(seq)
        if rec is None or rec["status"] != "pending":  # booked meanwhile (a failed dispatch)
            self.counters["late_or_unknown_results"] += 1
            return
        rec.update(result=now, rtt_ms=(now - rec["capture"]) * 1e3, local_infer_ms=infer_time * 1e3,
                   n_persons=len(scores))
        self.persons[seq] = (boxes, scores)
        self.finish(seq, "local_done")
        self.strategy.on_local_result(now - rec["capture"], service=service, cpu=cpu, capture=rec["capture"])
        self._observe(seq, LOCAL, boxes, scores, rec["capture"])

    def edge_result(self, seq: int, status: str, now: float, infer_time: float, queue_time: float,
                    boxes: np.ndarray, scores: np.ndarray, edge: str | None = None,
                    arrival: float = NAN) -> str:
        """Book the edge's answer; returns its bucket, ``unknown`` for a frame not in flight
        (late after its timeout, or never sent), or ``wrong_edge`` for an answer from another
        edge than the one the frame was sent to (``edge``: the answering edge; counted, the frame
        still waits for its own edge). ``arrival``: when the frame reached the edge, on the edge's
        clock (codec version 4; NaN from an older edge)."""
        rec = self.records.get(seq)
        if edge is not None and rec is not None and rec.get("edge") and rec["edge"] != edge and (
                seq in self.in_flight or seq in self.copies):
            self.counters["wrong_edge_results"] += 1
            return "wrong_edge"
        self._last_reply = now
        self._lost_streak = 0
        sent = self.in_flight.pop(seq, None)
        copy_sent = self.copies.pop(seq, None) if sent is None else None
        sent_at = sent if sent is not None else copy_sent
        if sent_at is None or rec is None:
            self.counters["late_or_unknown_results"] += 1
            return "unknown"
        reply = self._reply(rec, sent_at, now, infer_time, queue_time, status,
                            str(rec.get("edge") or edge or ""), arrival)
        if sent is None:  # a copy: a measurement only, the frame is detected locally
            rec["copy_rtt_ms"] = (now - sent_at) * 1e3
            self.counters["copies_answered"] += 1
            if status == "ok":
                self.strategy.on_edge_result(now - rec["capture"], reply)
                self._observe(seq, EDGE, boxes, scores, rec["capture"])
            else:
                self.strategy.on_edge_refused(reply, self.rules.reply_timeout)
            return "copy"
        rec.update(result=now, edge_infer_ms=infer_time * 1e3, edge_queue_ms=queue_time * 1e3)
        if status != "ok":
            bucket = "edge_dropped" if status == "dropped" else "edge_error"
            self.finish(seq, bucket)
            self.strategy.on_edge_refused(reply, self.rules.reply_timeout)
            return bucket
        rtt = now - rec["capture"]
        rec.update(rtt_ms=rtt * 1e3, n_persons=len(scores))
        self.persons[seq] = (boxes, scores)
        self.finish(seq, "edge_done")
        self.per_edge[str(rec.get("edge") or edge or "")] += 1
        self.strategy.on_edge_result(rtt, reply)
        if rec.get("probe"):
            self._probe_answered(now - sent, now)
        self._observe(seq, EDGE, boxes, scores, rec["capture"])
        return "edge_done"

    def _observe(self, seq: int, side: str, boxes: np.ndarray, scores: np.ndarray, capture: float) -> None:
        """The answer's detections to the strategy, last (the frame is booked whatever it does): a
        failure there is logged and counted, never the caller's (a Zenoh callback, the detector)."""
        try:
            self.strategy.observe(seq, side, boxes, scores, capture)
        except Exception as exc:
            self.counters["observe_errors"] += 1
            if self.counters["observe_errors"] <= 10:
                log.warning("the strategy could not take frame %d's detections: %s", seq, exc)

    def _reply(self, rec: dict[str, Any], sent: float, now: float, service: float, queued_at_edge: float,
               status: str, edge: str, arrival: float) -> EdgeReply:
        """The answer as the strategy sees it. A frame put before the previous one even reached the
        edge waited behind it on the link: the gap between their arrivals is the link's time for
        this frame's bytes, a sample of the rate it delivers (frames put later would count idle
        time too). From an edge that stamps the arrival (``arrival``, its clock), the gap between
        the stamps (robot/linkclock.py); from an older one, between the two answers, which also
        holds the edge's service times and the robot's stalls. Put, not handed to the sender
        (``sent``): a robot under a CPU quota may stall between the two for most of a scheduling
        period (100 ms), and a gap that holds the stall is no sample of the link."""
        nbytes = float(rec.get("bytes", NAN))
        put = float(rec.get("put", sent))
        link, excess = self.link_clock.answered(edge, arrival, float(rec.get("put_mono", NAN)),
                                                int(rec.get("put_n", -1)), now)
        stamped = math.isfinite(arrival)
        self.counters["answers_stamped"] += stamped
        if stamped != self._stamped:  # the encodings' base latency is the other kind of time
            self.encodings.base.samples.clear()
            self._stamped = stamped
        if status != "ok":  # an overflowing edge answers at once: no sample of its pace
            if rec.get("trial"):  # nor of the link: the trial is over, tried again later
                if status == "dropped":  # a newer frame came behind it: says nothing of the link
                    self.encodings.untried(now)
                else:
                    self._encoding_lost(rec, now)
                nbytes = NAN
            return EdgeReply(sent=sent, result=now, bytes=nbytes, service=service, status=status)
        queued = put < self._last_arrival and self._last_answer < now
        gap = link if stamped else now - self._last_answer if queued else NAN
        rec["link_ms"] = gap * 1e3  # the link's time for its bytes, when it queued (frames.csv)
        rate = nbytes / gap if math.isfinite(nbytes) and gap > 0 else NAN
        self._last_answer = now
        edge_time = sum(x for x in (service, queued_at_edge) if math.isfinite(x))
        self._last_arrival = now - edge_time  # when it reached the edge, near enough (robot clock)
        # The strategy sees a trial's time only: its size is not the others'. Nor the size of a
        # frame of the encoding just left (answered after the switch): its bytes, its rate and its
        # path time would be taken for the new encoding's
        other = bool(rec.get("trial"))
        if rec.get("encoding"):
            # from the put when known (the encoding and any stall before it left out)
            if self.encodings.answered(rec["encoding"], other, put, now, edge_time,
                                       0.0 if "put" in rec else float(rec.get("encode_ms", NAN)) / 1e3,
                                       service, gap, path=excess if stamped else None):
                self._encoding_switched()
            other = other or rec["encoding"] != self.encodings.current
            if other:
                nbytes = rate = NAN
        return EdgeReply(sent=sent, result=now, bytes=nbytes, service=service, delivery_rate=rate,
                         status=status, edge_queue=queued_at_edge,
                         alone=bool(rec.get("alone")) and not other)

    # Losses and fallback
    def expire(self, now: float) -> list[int]:
        """Book every edge frame unanswered for ``reply_timeout`` as lost; returns their seqs. An
        unanswered copy is only an observation."""
        expired = [(k, t) for k, t in self.copies.items() if now - t > self.rules.reply_timeout]
        self._drop_copies([seq for seq, _ in expired], now)
        for _, sent in expired:
            self.strategy.on_edge_timeout(now - sent)
        overdue = [seq for seq, sent in self.in_flight.items() if now - sent > self.rules.reply_timeout]
        for seq in overdue:
            self._book_lost(seq, now)
        self._lost_streak += len(overdue)
        # A frame lost now and then is the link's loss (counted, and the strategy sees it); an edge
        # that lets several frames in a row go unanswered, and answered nothing for a whole
        # timeout, is gone
        if (overdue and self._lost_streak >= self.rules.fallback_losses
                and now - self._last_reply > self.rules.reply_timeout):
            self._enter_fallback(now, f"{self._lost_streak} edge frames in a row unanswered")
        return overdue

    def edges_changed(self, present: bool, now: float) -> None:
        """The edge-presence watcher's news: the last edge gone books everything in flight lost."""
        self.edge_present = present
        if not present:
            self.link_clock.reset()  # an edge that comes back may be another process, another clock
            self._drop_copies(list(self.copies), now)
            for seq in list(self.in_flight):
                self._book_lost(seq, now)
            self._enter_fallback(now, "edge liveliness lost")

    def edge_gone(self, edge: str, now: float) -> list[int]:
        """One edge's token went while others stay: the frames (and copies) sent to it will not be
        answered, booked lost at once; returns their seqs. (The last edge going is
        ``edges_changed``.)"""
        lost = [seq for seq in self.in_flight if self.records[seq].get("edge") == edge]
        for seq in lost:
            self._book_lost(seq, now)
        self._drop_copies([k for k in self.copies if self.records[k].get("edge") == edge], now)
        return lost

    def _drop_copies(self, seqs: list[int], now: float) -> None:
        """Copies that will not be answered (timed out, their edge went, or the run ends): counted,
        and a trial of raw frames among them is over."""
        for seq in seqs:
            del self.copies[seq]
            self.counters["copies_lost"] += 1
            self._last_loss = now
            self._encoding_lost(self.records[seq], now)

    def _book_lost(self, seq: int, now: float) -> None:
        self.in_flight.pop(seq, None)
        self._last_loss = now
        self.finish(seq, "edge_lost")
        rec = self.records[seq]
        self._encoding_lost(rec, now)
        self.strategy.on_edge_timeout(now - rec["send"])
        if rec.get("probe"):
            self._probe_streak = 0

    def _enter_fallback(self, now: float, why: str) -> None:
        if not self.fallback:
            self.fallback = True
            self._probe_streak = 0
            self.counters["fallbacks"] += 1
            self.fallback_events.append({"start": now, "end": float("nan")})
            del self.fallback_events[:-MAX_FALLBACK_EVENTS]  # a flapping link for days: the newest
            log.warning("fallback to local detection: %s", why)

    def _probe_answered(self, waited: float, now: float) -> None:
        if not self.fallback:
            return
        self._probe_streak = self._probe_streak + 1 if waited <= self.rules.reply_timeout else 0
        if self._probe_streak >= self.rules.resume_after:
            self.fallback = False
            self.fallback_events[-1]["end"] = now
            log.info("edge answers again: offloading resumes")

    # End of run and totals
    def close(self, now: float, send_waiting: int | None, local_waiting: int | None) -> None:
        """Book what is left: the frame waiting for the link, the frames in flight, the frame
        waiting for the local detector."""
        if send_waiting is not None:
            self.send_replaced(send_waiting)
        self._drop_copies(list(self.copies), now)
        for seq in list(self.in_flight):
            self._book_lost(seq, now)
        if local_waiting is not None:
            self.local_replaced(local_waiting)

    def balance(self) -> dict[str, int]:
        out = {k: int(self.counters[k]) for k in ("frames_in", *DONE, *DROPPED)}
        out["pending"] = sum(1 for r in self.records.values() if r["status"] == "pending")
        return out

    def balanced(self) -> bool:
        b = self.balance()
        return b["frames_in"] == sum(b[k] for k in (*DONE, *DROPPED)) + b["pending"]

    def summary(self, monitor: dict[str, float | None] | None = None) -> dict[str, Any]:
        """The run in figures, as the offloading thesis reports it, with the ``monitor``'s means
        over the run (CPU, Mbps, power, ping, sampled once a second). Exact however many records
        retired: the per-frame means are running sums (robot/framelog.py)."""
        bal, totals = self.balance(), self.log.totals_now()
        done = bal["local_done"] + bal["edge_done"]
        m = monitor or {}
        return {
            "balance": bal,
            "balanced": self.balanced(),
            "processed_pct": 100.0 * done / bal["frames_in"] if bal["frames_in"] else 0.0,
            "offloaded_pct": 100.0 * self.strategy.offloaded / max(self.strategy.total, 1),
            **totals.figures(),
            "cpu_process_pct": m.get("cpu_process"),
            "cpu_system_pct": m.get("cpu_system"),
            "mbps_out": m.get("mbps_out"),
            "power_w": m.get("power_w"),
            "ping_ms": m.get("ping_ms"),
            "fallbacks": list(self.fallback_events),
            "records_retired": self.log.retired,
            "records_on_disk": self.log.folder is not None,
            "per_edge": dict(self.per_edge),
            "other": {k: v for k, v in self.counters.items() if k not in bal},
            "edge_spares": getattr(self.strategy, "spares", None),  # dispatch's frames beyond its depth
            "edge_retries": getattr(self.strategy, "retries", None),  # dispatch's frames to a blocked edge
            "local_overflows": getattr(self.strategy, "overflows", None),  # dispatch's, the edge path full
            "overflow_gap_s": (round(float(self.strategy.overflow_gap), 3)  # their spacing, at the end
                               if hasattr(self.strategy, "overflow_gap") else None),
            "edge_drains": getattr(self.strategy, "drains", None),  # dispatch's drains to measure the base
            "local_bias": getattr(self.strategy, "bias_summary", lambda: None)(),  # dispatch's, learnt or set
            "encodings": self.encodings.summary(),
            # answers stamped with the frame's arrival (codec version 4), the link samples taken
            # from them, and how often another edge clock made the link clock start again
            "link_clock": {"stamped": self.counters["answers_stamped"], "samples": self.link_clock.samples,
                           "resets": self.link_clock.resets},
        }
