"""Where a Ray sweep's driver sends the queue's next chunk (`ray_plan.choose_engine`), on
given engines and records: the live hand-out is tested on a Ray cluster in
test_sweep_ray.py; here a small clock-driven model of batched engines checks what the
placement promises (every engine that starts gets work, none holds more than its share while
others wait, each chunk given once)."""

from __future__ import annotations

from vabench.sweep.ray_plan import Chunk, EngineHandle, choose_engine

LIMIT = 1024  # an engine's in-flight limit (its status's "limit"): large, as on a GPU


def _engines(n: int) -> list[EngineHandle]:
    return [
        EngineHandle(index=i, actor=None, holder="node", starting=object(), status={"limit": LIMIT})
        for i in range(n)
    ]


def _plan(tasks: int, episodes: int, cost: int = 10) -> list[Chunk]:
    return [
        Chunk(f"t{t}", [("m", "active", f"t{t}", s, 1) for s in range(episodes)], cost)
        for t in range(tasks)
    ]


def _hand_out(engines, queue, records, max_chunks=8):
    """The driver's loop body (`ClusterSweep._hand_out`) on plain lists."""
    given = []
    while queue:
        queued = sum(len(c.keys) * c.cost for c in queue)
        best = choose_engine(engines, queue[0], records, queued, max_chunks)
        if best is None:
            break
        chunk = queue.pop(0)
        best.chunks[object()] = chunk
        given.append((best.index, chunk.name))
    return given


def _run(engines, queue, ready_at, seconds_per_episode=1.0):
    """Every engine steps all its chunks' episodes at once (one batch per task): each chunk
    records one episode every `seconds_per_episode` x its cost / 10. Returns the time each
    engine worked until, and every chunk's engine."""
    records: dict = {}
    placed: dict[str, int] = {}
    progress: dict[int, float] = {}  # id(chunk) -> episodes done (fractional)
    busy_until = dict.fromkeys(range(len(engines)), 0.0)
    t, dt = 0.0, 0.1
    while queue or any(e.chunks for e in engines):
        for e in engines:
            if e.starting is not None and t >= ready_at[e.index]:
                e.starting = None
        for index, name in _hand_out(engines, queue, records):
            assert name not in placed, f"{name} given twice"
            placed[name] = index
        for e in engines:
            for ref, chunk in list(e.chunks.items()):
                done = progress.get(id(chunk), 0.0) + dt / (seconds_per_episode * chunk.cost / 10)
                progress[id(chunk)] = done
                for k in chunk.keys[: int(done)]:
                    records[k] = True
                if int(done) >= len(chunk.keys):
                    del e.chunks[ref]
                    busy_until[e.index] = t + dt
        t += dt
        assert t < 10_000, "the model never ended"
    return busy_until, placed


def test_engines_that_start_later_still_get_their_share_of_the_plan():
    """The placement measured on 4 x H100 (2026-11-27): 14 families of 12 episodes, the
    engines ready at 12.4, 12.6, 13.8 and 12.6 s; the first two ready took every chunk
    (8 and 6), the other two none."""
    engines = _engines(4)
    ready_at = [12.4, 12.6, 13.8, 12.6]
    queue = _plan(14, 12)
    busy_until, placed = _run(engines, queue, ready_at)
    per_engine = [sum(1 for i in placed.values() if i == e) for e in range(4)]
    assert sorted(placed) == sorted(f"t{t}" for t in range(14))
    assert min(per_engine) >= 3, per_engine  # 14 chunks: 3 or 4 each
    # a batched engine takes as long for 3 chunks as for 1: the plan ends close to one
    # chunk's time after the last engine started, not with 2 engines doing it all
    assert max(busy_until.values()) < 13.8 + 2 * 12 + 1


def test_the_first_engine_ready_takes_only_its_fair_share():
    engines = _engines(4)
    engines[0].starting = None  # ready; the other three still starting
    queue = _plan(14, 12)
    given = _hand_out(engines, queue, {})
    assert [i for i, _ in given] == [0, 0, 0]  # 3 x 120 <= 1,680 / 4 < 4 x 120
    assert len(queue) == 11  # waiting for the others


def test_one_engine_takes_the_whole_plan_up_to_its_limits():
    engines = _engines(1)
    engines[0].starting = None
    queue = _plan(6, 12)
    assert len(_hand_out(engines, queue, {})) == 6
    queue = _plan(12, 12)
    assert len(_hand_out(_ready(_engines(1)), queue, {}, max_chunks=8)) == 8  # max_chunks
    small = _ready(_engines(1))
    small[0].status["limit"] = 10  # 2 x 10 episodes held at most
    assert len(_hand_out(small, _plan(6, 12), {})) == 2


def test_an_idle_engine_takes_a_chunk_larger_than_its_share():
    """The basket: 60 long episodes cost more than a fair share of the whole plan; the engine
    it goes to holds it alone while the others share the rest."""
    engines = _ready(_engines(3))
    basket = Chunk("basket", [("m", "active", "basket", s, 1) for s in range(60)], 100)
    queue = [basket, *_plan(6, 12)]
    given = _hand_out(engines, queue, {})
    assert given[0] == (0, "basket")
    assert all(i != 0 for i, _ in given[1:])
    assert not queue  # 6 x 120 shared by the two others: 3 each


def test_a_dead_engine_neither_takes_work_nor_counts_in_the_share():
    engines = _ready(_engines(3))
    engines[2].dead = True
    queue = _plan(6, 12)
    given = _hand_out(engines, queue, {})
    assert {i for i, _ in given} == {0, 1}
    assert not queue  # the share is the plan over 2 engines, not 3


def test_recorded_episodes_lighten_an_engines_load():
    engines = _ready(_engines(2))
    queue = _plan(5, 12)
    _hand_out(engines, queue, {})
    assert len(queue) == 1  # 2 + 2 chunks, the fifth over both shares
    first = next(iter(engines[0].chunks.values()))
    records = dict.fromkeys(first.keys, True)  # engine 0's first chunk recorded
    given = _hand_out(engines, queue, records)
    assert given == [(0, "t4")]


def _ready(engines: list[EngineHandle]) -> list[EngineHandle]:
    for e in engines:
        e.starting = None
    return engines


def test_an_engine_that_never_starts_stops_holding_a_share():
    """Ray may leave an engine pending for good (its GPU held by another job): after
    `START_GRACE_S` the ready engines share the plan without it."""
    from vabench.sweep.ray_plan import START_GRACE_S

    engines = _engines(2)
    engines[0].starting = None
    queue = _plan(4, 12)  # 4 x 120
    for _ in range(2):
        engines[0].chunks[object()] = queue.pop(0)  # half the plan: its share of two
    queued = sum(len(c.keys) * c.cost for c in queue)
    asked = engines[1].clock.asked_at
    soon, late = asked + START_GRACE_S - 1, asked + START_GRACE_S + 1
    assert choose_engine(engines, queue[0], {}, queued, 8, now=soon) is None
    assert choose_engine(engines, queue[0], {}, queued, 8, now=late) is engines[0]
