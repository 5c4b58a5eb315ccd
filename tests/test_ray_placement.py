"""Where a Ray sweep's driver sends the queue's next chunk (`placement.choose_engine`), on
given engines and records: the live hand-out is tested on a Ray cluster in
test_sweep_ray.py; here a small clock-driven model of batched engines checks what the
placement promises (every engine that starts gets work, none holds more than its share while
others wait, each chunk given once)."""

from __future__ import annotations

from vabench.sweep.placement import Chunk, EngineHandle, choose_engine, next_placement
from vabench.sweep.plan import EpisodeKey
from vabench.sweep.results import ledger_key

LIMIT = 1024  # an engine's in-flight limit (its status's "limit"): large, as on a GPU


def _engines(n: int) -> list[EngineHandle]:
    return [EngineHandle(index=i, status={"limit": LIMIT}) for i in range(n)]


def _plan(tasks: int, episodes: int, cost: int = 10) -> list[Chunk]:
    return [
        Chunk(f"t{t}", [EpisodeKey("m", "active", f"t{t}", s, 1) for s in range(episodes)], cost)
        for t in range(tasks)
    ]


def _hand_out(engines, queue, records, max_chunks=8):
    """The driver's loop body (`Driver._hand_out`) on plain lists."""
    given = []
    while queue:
        placed = next_placement(engines, queue, records, max_chunks)
        if placed is None:
            break
        at, best = placed
        chunk = queue.pop(at)
        best.chunks[object()] = chunk
        given.append((best.index, chunk.name))
    return given


def _run(engines, queue, ready_at, seconds_per_episode=1.0, watch=None):
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
            if e.starting and t >= ready_at[e.index]:
                e.starting = False
        for index, name in _hand_out(engines, queue, records):
            assert name not in placed, f"{name} given twice"
            placed[name] = index
        if watch is not None:
            watch(engines)
        for e in engines:
            for ref, chunk in list(e.chunks.items()):
                done = progress.get(id(chunk), 0.0) + dt / (seconds_per_episode * chunk.cost / 10)
                progress[id(chunk)] = done
                for k in chunk.keys[: int(done)]:
                    records[ledger_key(k)] = True
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
    engines[0].starting = False  # ready; the other three still starting
    queue = _plan(14, 12)
    given = _hand_out(engines, queue, {})
    assert [i for i, _ in given] == [0, 0, 0]  # 3 x 120 <= 1,680 / 4 < 4 x 120
    assert len(queue) == 11  # waiting for the others


def test_one_engine_takes_the_whole_plan_up_to_its_limits():
    engines = _engines(1)
    engines[0].starting = False
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
    basket = Chunk("basket", [EpisodeKey("m", "active", "basket", s, 1) for s in range(60)], 100)
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
    records = dict.fromkeys(map(ledger_key, first.keys), True)  # engine 0's first chunk recorded
    given = _hand_out(engines, queue, records)
    assert given == [(0, "t4")]


def _ready(engines: list[EngineHandle]) -> list[EngineHandle]:
    for e in engines:
        e.starting = False
    return engines


def test_an_engine_that_never_starts_stops_holding_a_share():
    """Ray may leave an engine pending for good (its GPU held by another job): after
    `START_GRACE_S` the ready engines share the plan without it."""
    from vabench.sweep.placement import START_GRACE_S

    engines = _engines(2)
    engines[0].starting = False
    queue = _plan(4, 12)  # 4 x 120
    for _ in range(2):
        engines[0].chunks[object()] = queue.pop(0)  # half the plan: its share of two
    queued = sum(len(c.keys) * c.cost for c in queue)
    asked = engines[1].clock.asked_at
    soon, late = asked + START_GRACE_S - 1, asked + START_GRACE_S + 1
    assert choose_engine(engines, queue[0], {}, queued, 8, now=soon) is None
    assert choose_engine(engines, queue[0], {}, queued, 8, now=late) is engines[0]


def _on_gpus(engines: list[EngineHandle], per_gpu: int) -> list[EngineHandle]:
    """Engines sharing GPUs, `per_gpu` a GPU, as their start replies say (`info["gpus"]`)."""
    for e in engines:
        e.info = {"node": "n1", "gpus": [str(e.index // per_gpu)]}
    return engines


def _critical(n: int, episodes: int, cost: int) -> list[Chunk]:
    return [
        Chunk(
            f"basket {i}",
            [EpisodeKey("m", "active", "basket", i * episodes + s, 1) for s in range(episodes)],
            cost,
            critical=True,
        )
        for i in range(n)
    ]


def test_the_critical_paths_chunks_run_alone_one_a_gpu():
    """`configs/all.yaml` on 4 GPUs x 4 engines (4 x H200, 2026-11-28): the basket's four chunks
    of 15 episodes first in the queue, then 28 chunks of the other families. Each basket chunk
    goes to an engine of its own on a GPU of its own, even where the first engines ready share
    a GPU, and that engine takes nothing else while it runs it; every chunk is given once and
    every engine gets work."""
    engines = _on_gpus(_engines(16), per_gpu=4)
    ready_at = [8.0 + 0.1 * i for i in range(16)]  # GPU 0's engines first
    queue = [*_critical(4, 15, 250), *_plan(28, 15, 50)]
    alone = []

    def watch(engines):
        for e in engines:
            kinds = [c.critical for c in e.chunks.values()]
            if any(kinds):
                alone.append(kinds == [True])

    _, placed = _run(engines, queue, ready_at, watch=watch)
    assert len(placed) == 32
    gpus = [engines[placed[f"basket {i}"]].gpu for i in range(4)]
    assert len(set(gpus)) == 4, gpus
    assert alone and all(alone)
    assert {placed[f"t{t}"] for t in range(28)} | {placed[f"basket {i}"] for i in range(4)} == set(
        range(16)
    )


def test_a_critical_chunk_does_not_leave_the_rest_without_an_engine():
    """One engine runs the basket with everything else. With two, the first basket chunk is
    alone and the second is placed as any other chunk (on the other engine, the one left for
    the rest); every engine then holding one, the rest is shared by both as before."""
    one = _ready(_on_gpus(_engines(1), per_gpu=4))
    queue = [*_critical(1, 15, 250), *_plan(4, 15, 50)]
    assert next_placement([], queue, {}, 8) is None  # before any engine is asked for
    assert [i for i, _ in _hand_out(one, queue, {})] == [0] * 5
    two = _ready(_on_gpus(_engines(2), per_gpu=4))
    queue = [*_critical(2, 15, 250), *_plan(4, 15, 50)]
    given = _hand_out(two, queue, {})
    assert given[0] == (0, "basket 0") and given[1][1] == "basket 1"
    assert given[1] == (1, "basket 1")
    assert {i for i, _ in given[2:]} == {0, 1} and not queue
    three = _ready(_on_gpus(_engines(3), per_gpu=4))
    queue = [*_critical(1, 15, 250), *_plan(4, 15, 50)]
    given = _hand_out(three, queue, {})
    assert given[0] == (0, "basket 0") and all(i != 0 for i, _ in given[1:]), given


def test_a_critical_chunk_waits_for_engines_still_starting_then_doubles_up():
    """Two engines ready on GPU 0, one of them running a basket chunk, a third engine starting:
    the next basket chunk waits for it (it may sit on another GPU) for `CRITICAL_WAIT_S`, then
    takes the idle engine on GPU 0."""
    from vabench.sweep.placement import CRITICAL_WAIT_S

    engines = _on_gpus(_engines(4), per_gpu=2)
    for e in engines[:2]:
        e.starting = False
    first, second = _critical(2, 15, 250)
    engines[0].chunks[object()] = first
    asked = engines[2].clock.asked_at
    soon, late = asked + CRITICAL_WAIT_S - 1, asked + CRITICAL_WAIT_S + 1
    assert choose_engine(engines, second, {}, 0, 8, now=soon) is None
    assert choose_engine(engines, second, {}, 0, 8, now=late) is engines[1]
    engines[2].starting = False
    engines[2].info = {"node": "n1", "gpus": ["1"]}
    assert choose_engine(engines, second, {}, 0, 8, now=soon) is engines[2]
    other = _plan(1, 15, 50)[0]  # a chunk off the critical path never joins a basket chunk
    assert choose_engine(engines, other, {}, 750, 8, now=soon) is engines[1]


def test_the_ready_engines_work_while_a_critical_chunk_waits_for_the_others():
    """Only GPU 0's four engines ready, twelve on three GPUs still starting: the first basket
    chunk goes to GPU 0, the other three wait for the other GPUs' engines, and meanwhile GPU
    0's three other engines take the chunks behind them; a late replacement engine is not
    waited for."""
    from vabench.sweep.placement import CRITICAL_WAIT_S

    engines = _on_gpus(_engines(16), per_gpu=4)
    for e in engines[:4]:
        e.starting = False
    queue = [*_critical(4, 15, 250), *_plan(28, 15, 50)]
    given = _hand_out(engines, queue, {})
    assert given[0] == (0, "basket 0")
    assert {i for i, _ in given[1:]} == {1, 2, 3} and all(n.startswith("t") for _, n in given[1:])
    assert [c.name for c in queue[:3]] == ["basket 1", "basket 2", "basket 3"]
    late = engines[0].clock.asked_at + CRITICAL_WAIT_S + 1
    for e in engines[4:]:
        e.clock.asked_at = late - 2  # replacements asked for after the sweep's first minute
    engines[1].chunks.clear()  # GPU 0's engine 1 idle again
    placed = next_placement(engines, queue, {}, 8, now=late)
    assert placed is not None and placed[0] == 0 and placed[1] is engines[1]


def test_a_critical_chunk_placed_as_any_other_counts_its_own_cost_in_the_share():
    """One busy engine and the basket's chunk queued before another: both still go to it (the
    share that judges the basket's chunk includes its cost)."""
    engines = _ready(_on_gpus(_engines(1), per_gpu=4))
    engines[0].chunks[object()] = _plan(1, 15, 50)[0]
    queue = [*_critical(1, 15, 250), *_plan(1, 15, 50)]
    queue[1].name = "t1"
    assert [n for _, n in _hand_out(engines, queue, {})] == ["basket 0", "t1"]


def _ranked(engines: list[EngineHandle], per_gpu: int) -> list[EngineHandle]:
    """Engines sharing GPUs in a ranked sweep: the first of each GPU normal, the others below
    normal, as their start replies' environments say."""
    from vabench.tuning import mps

    for e in _on_gpus(engines, per_gpu):
        first = e.index % per_gpu == 0
        e.info["environment"] = {mps.PRIORITY_VARIABLE: mps.NORMAL if first else mps.BELOW_NORMAL}
    return engines


def test_critical_chunks_go_to_their_gpus_normal_priority_engine():
    """A ranked sweep on 4 GPUs x 4 engines, each GPU's lead (its one normal MPS client) ready
    last: every basket chunk waits for its GPU's lead rather than take a below-normal engine,
    while the others take the rest; all four end on the four leads."""
    engines = _ranked(_engines(16), per_gpu=4)
    ready_at = [9.0 if i % 4 == 0 else 8.0 + 0.01 * i for i in range(16)]
    queue = [*_critical(4, 15, 250), *_plan(28, 15, 50)]
    _, placed = _run(engines, queue, ready_at)
    leads = {placed[f"basket {i}"] for i in range(4)}
    assert leads == {0, 4, 8, 12}, leads
    assert all(engines[i].lead for i in leads) and not engines[1].lead


def test_a_critical_chunk_takes_a_below_normal_engine_once_the_wait_is_over():
    """GPU 0's lead not ready: the basket chunk waits for it within `CRITICAL_WAIT_S`, then
    takes an idle engine of that GPU at below-normal priority rather than wait for the whole
    sweep; with the lead gone there is nothing to wait for."""
    from vabench.sweep.placement import CRITICAL_WAIT_S

    engines = _ranked(_engines(4), per_gpu=4)
    for e in engines[1:]:
        e.starting = False
    chunk = _critical(1, 15, 250)[0]
    asked = engines[0].clock.asked_at
    assert choose_engine(engines, chunk, {}, 0, 8, now=asked + CRITICAL_WAIT_S - 1) is None
    late = choose_engine(engines, chunk, {}, 0, 8, now=asked + CRITICAL_WAIT_S + 1)
    assert late is engines[1]
    engines[0].dead = True  # gone: nothing left to wait for
    assert choose_engine(engines, chunk, {}, 0, 8, now=asked + 1) is engines[1]


def test_a_critical_chunk_does_not_wait_for_a_lead_already_at_work():
    """GPU 0's lead ready and busy with another family, GPU 1's engines still starting: an idle
    below-normal engine of GPU 0 takes the basket chunk at once (the lead would stay busy);
    where GPU 0's lead is the one still starting, the chunk waits instead."""
    engines = _ranked(_engines(8), per_gpu=4)
    for e in engines[:4]:
        e.starting = False
    engines[0].chunks[object()] = _plan(1, 15, 50)[0]
    chunk = _critical(1, 15, 250)[0]
    soon = engines[0].clock.asked_at + 1
    assert choose_engine(engines, chunk, {}, 0, 8, now=soon) is engines[1]
    engines[0].chunks.clear()
    engines[0].starting = True
    assert choose_engine(engines, chunk, {}, 0, 8, now=soon) is None
