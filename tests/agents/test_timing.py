"""agents.timing: a process's CPU time per frame counts its own work from the first frame on, not its start-up
and not the time it waited."""

from __future__ import annotations

import time

from agents.timing import StageTimer


def _spin(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def test_cpu_per_frame_counts_work_not_waits_nor_start_up() -> None:
    timer = StageTimer()
    _spin(0.2)  # start-up: before the first stage, not counted
    assert timer.cpu_ms() is None and timer.to_json()["cpu_ms_per_frame"] is None
    for _ in range(2):
        with timer.stage("wait"):
            time.sleep(0.1)  # waiting costs no CPU
        with timer.stage("fusion"):
            _spin(0.05)
        timer.frame_done()
    cpu = timer.cpu_ms()
    assert cpu is not None and 45 <= cpu < 90, cpu  # 50 ms of work a frame, neither the sleep nor the 200 ms
    doc = timer.to_json()
    assert doc["cpu_ms_per_frame"] == cpu or abs(doc["cpu_ms_per_frame"] - cpu) < 5
    assert doc["ms_per_frame"]["wait"] >= 95  # the wall time still says where the frame went


def test_method_ms_sums_each_methods_fusion_and_decoding() -> None:
    timer = StageTimer()
    for stage, ms in (("fusion.cobevt", 60.0), ("decoding.cobevt", 10.0), ("fusion.none", 1.0), ("comm", 5.0),
                      ("decoding.none", 9.0), ("wait", 300.0)):
        timer.add(stage, ms)
    assert timer.method_ms() == {"cobevt": 70.0, "none": 10.0}


def test_reading_method_costs_while_another_thread_times_new_stages_never_fails():
    """The ego's scoring thread times stages on the timer the main thread reads while fusing: a stage first
    timed mid-read once raised "dictionary changed size during iteration" in the ego (CI, a live run)."""
    import sys
    import threading

    timer = StageTimer()
    done = threading.Event()

    def writer() -> None:
        for i in range(3000):  # each a new stage: the dict grows while it is read
            timer.add(f"fusion.m{i}", 1.0)
        done.set()

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as possible: the race shows within milliseconds
    t = threading.Thread(target=writer)
    t.start()
    try:
        while not done.is_set():
            timer.method_ms()
            timer.split()
    finally:
        t.join()
        sys.setswitchinterval(old)
    assert len(timer.method_ms()) == 3000
