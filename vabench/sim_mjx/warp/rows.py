"""The Warp batch's kernels over per-slot rows, around the physics: the merge, the commit, and
moving rows between slots, the host and the renderer.

- the merge: `Snapshot` saves the rows an action may change (qpos, qvel, ctrl, warm start,
  act, time) before its substeps and gives slots that must not advance (idle, invalid, failed
  plan) their saved rows back bit for bit;
- the commit: `finish_action` / `finish_hold` record the gripper command of slots that moved and
  their buffer overflow bits; `count_substep` is the device counter the references read;
- moving rows: `scatter_rows` / `scatter` (`set_state`), `gather_rows` (the renderer's qpos);
- `contact_flags`: the predicates' watched contact pairs per slot, from MuJoCo Warp's contacts.
"""

from __future__ import annotations

from typing import Any

import warp as wp


@wp.kernel
def save_rows(src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)):
    w, j = wp.tid()
    dst[w, j] = src[w, j]


@wp.kernel
def restore_rows(
    keep: wp.array(dtype=int), saved: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)
):
    """Rows of worlds whose physics must not advance get their saved values back."""
    w, j = wp.tid()
    if keep[w] == 0:
        dst[w, j] = saved[w, j]


@wp.kernel
def restore_time(keep: wp.array(dtype=int), saved: wp.array(dtype=float), t: wp.array(dtype=float)):
    w = wp.tid()
    if keep[w] == 0:
        t[w] = saved[w]


class Snapshot:
    """Saved copies of `rows` ((N, k) float arrays; those with k = 0 are skipped) and of the
    per-world `time`, for the merge."""

    def __init__(self, rows: list[wp.array], time: wp.array):
        self.rows = [a for a in rows if a.shape[1]]
        self.saved = [wp.empty_like(a) for a in self.rows]
        self.time = time
        self.saved_time = wp.empty_like(time)

    def save(self) -> None:
        for src, dst in zip(self.rows, self.saved, strict=True):
            wp.launch(save_rows, dim=src.shape, inputs=[src, dst])
        wp.copy(self.saved_time, self.time)

    def restore(self, keep: wp.array) -> None:
        """Worlds with keep[w] == 0 get their saved rows and time back."""
        for dst, saved in zip(self.rows, self.saved, strict=True):
            wp.launch(restore_rows, dim=dst.shape, inputs=[keep, saved, dst])
        wp.launch(restore_time, dim=self.time.shape[0], inputs=[keep, self.saved_time, self.time])


@wp.kernel
def mark_rest(
    k: wp.array(dtype=int),
    rest_from: wp.array(dtype=int),
    rest_speed: wp.array(dtype=float),
    go: wp.array(dtype=int),
    qvel: wp.array2d(dtype=float),
    done: wp.array(dtype=int),
    newly: wp.array(dtype=int),
    substeps: wp.array(dtype=int),
):
    """An action ending at rest (controller.ACTION_ENDS), after substep k[0]: a slot that acts
    and has not ended ends now when its references are final (k[0] >= rest_from[w]) and every
    dof j is slower than rest_speed[j] (scene.rest_speeds). newly[w]: it ended at this substep
    (its rows are saved now); substeps[w]: the substeps its action ran."""
    w = wp.tid()
    newly[w] = 0
    if go[w] == 0 or done[w] != 0:
        return
    substeps[w] = k[0]
    if k[0] < rest_from[w]:
        return
    for j in range(qvel.shape[1]):
        if wp.abs(qvel[w, j]) >= rest_speed[j]:
            return
    done[w] = 1
    newly[w] = 1


@wp.kernel
def rest_condition(
    k: wp.array(dtype=int),
    n: int,
    go: wp.array(dtype=int),
    done: wp.array(dtype=int),
    go_on: wp.array(dtype=wp.int32),
):
    """The device loop's condition for an action ending at rest: below n substeps and some
    acting slot still moving (one thread: a few dozen slots)."""
    busy = wp.int32(0)
    if k[0] < n:
        for w in range(go.shape[0]):
            if go[w] != 0 and done[w] == 0:
                busy = wp.int32(1)
    go_on[0] = busy


@wp.kernel
def copy_rows_where(
    mask: wp.array(dtype=int), src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)
):
    w, j = wp.tid()
    if mask[w] != 0:
        dst[w, j] = src[w, j]


@wp.kernel
def copy_where(mask: wp.array(dtype=int), src: wp.array(dtype=float), dst: wp.array(dtype=float)):
    w = wp.tid()
    if mask[w] != 0:
        dst[w] = src[w]


@wp.kernel
def fixed_substeps(go: wp.array(dtype=int), k: wp.array(dtype=int), substeps: wp.array(dtype=int)):
    w = wp.tid()
    substeps[w] = wp.where(go[w] != 0, k[0], 0)


class RestRows:
    """The rows (as `Snapshot`'s) of each slot at the substep its action came to rest: saved
    then, given back after the loop, so that a slot's final state is that of its own rest
    substep however long the loop ran for the other slots."""

    def __init__(self, snapshot: Snapshot):
        self.rows = snapshot.rows
        self.saved = [wp.empty_like(a) for a in self.rows]
        self.time = snapshot.time
        self.saved_time = wp.empty_like(self.time)

    def save(self, mask: wp.array) -> None:
        for src, dst in zip(self.rows, self.saved, strict=True):
            wp.launch(copy_rows_where, dim=src.shape, inputs=[mask, src, dst])
        wp.launch(copy_where, dim=self.time.shape[0], inputs=[mask, self.time, self.saved_time])

    def restore(self, mask: wp.array) -> None:
        for dst, saved in zip(self.rows, self.saved, strict=True):
            wp.launch(copy_rows_where, dim=dst.shape, inputs=[mask, saved, dst])
        wp.launch(copy_where, dim=self.time.shape[0], inputs=[mask, self.saved_time, self.time])


@wp.kernel
def count_substep(k: wp.array(dtype=int)):
    """One more substep done (the references of the next one read k)."""
    k[0] = k[0] + 1


@wp.kernel
def finish_action(
    go: wp.array(dtype=int),
    cmd_grip: wp.array2d(dtype=int),
    overflow: wp.array(dtype=int),
    failure_bits: int,
    grip_open: wp.array2d(dtype=int),
    failed: wp.array(dtype=int),
):
    """Commit the gripper command of slots that moved; record overflow of those slots."""
    w, a = wp.tid()
    if go[w] == 0:
        return
    g = cmd_grip[w, a]
    if g >= 0:
        grip_open[w, a] = wp.where(g == 1, 1, 0)
    if a == 0:
        failed[w] = overflow[w] & failure_bits


@wp.kernel
def finish_hold(
    mask: wp.array(dtype=int),
    overflow: wp.array(dtype=int),
    failure_bits: int,
    failed: wp.array(dtype=int),
):
    w = wp.tid()
    if mask[w] != 0:
        failed[w] = failed[w] | (overflow[w] & failure_bits)  # ORed over the chunks of a hold


@wp.kernel
def scatter_rows(idx: wp.array(dtype=int), rows: wp.array2d(dtype=Any), dst: wp.array2d(dtype=Any)):
    """Row i of `rows` into row idx[i] of `dst` (float state rows and int grip rows alike)."""
    i, j = wp.tid()
    dst[idx[i], j] = rows[i, j]


# Declared here, not made at the first launch: a new overload reloads the module, which must
# not happen once graphs that use its kernels are captured.
for _dtype in (float, int):
    wp.overload(
        scatter_rows,
        {"rows": wp.array2d(dtype=_dtype), "dst": wp.array2d(dtype=_dtype)},
    )


@wp.kernel
def scatter(idx: wp.array(dtype=int), values: wp.array(dtype=float), dst: wp.array(dtype=float)):
    i = wp.tid()
    dst[idx[i]] = values[i]


@wp.kernel
def gather_rows(
    idx: wp.array(dtype=int), src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float)
):
    i, j = wp.tid()
    dst[i, j] = src[idx[i], j]


@wp.kernel
def contact_flags(
    nacon: wp.array(dtype=int),
    geom: wp.array(dtype=wp.vec2i),
    dist: wp.array(dtype=float),
    worldid: wp.array(dtype=int),
    side_a: wp.array2d(dtype=int),
    side_b: wp.array2d(dtype=int),
    flags: wp.array2d(dtype=int),
):
    """flags[w, p] = 1 when a touching contact (dist <= 0) of world w joins a geom of side_a[p]
    and one of side_b[p] (either order). Every writer writes 1: no race matters."""
    c = wp.tid()
    if c >= nacon[0] or dist[c] > 0.0:
        return
    g1, g2 = geom[c][0], geom[c][1]
    if g1 < 0 or g2 < 0:
        return
    w = worldid[c]
    for p in range(side_a.shape[0]):
        hit = (side_a[p, g1] != 0 and side_b[p, g2] != 0) or (
            side_a[p, g2] != 0 and side_b[p, g1] != 0
        )
        if hit:
            flags[w, p] = 1
