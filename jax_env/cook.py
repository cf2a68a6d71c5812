"""The scripted cook as a pure jittable function: observations -> each seat's action logits, with its convention as
arrays, so that one XLA program holds kitchens of many conventions at once (a row's convention is that row's arrays).

It plans as `torch_kitchen.partners.scripted_cook.ScriptedCook` does (its docstring says how), on the same
observation; where the torch cook reads distances off a table per floor plan kept on the host, this one runs the
breadth-first waves inside the program, a fixed number of steps (the kitchen's cells), so it has static shapes and no
host round trip. `CookConvention` holds what the torch cook derives from a `Convention`
(`torch_kitchen.partners.scripted_cook.cook_convention`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jax_env.env import INTERACT, NUM_ACTIONS, STAY
from jax_env.observation import Channel

UNREACHABLE = 1e4  # a distance longer than any path in a kitchen
# The goal list's shape (its events and roles: torch_kitchen.partners.scripted_cook.GOALS, which `cook_convention`
# scores): what each goal does on arrival beside its tile, the hand-over's and idling's places in it.
ON_ARRIVAL = (INTERACT, INTERACT, INTERACT, STAY, INTERACT, INTERACT, INTERACT, INTERACT, INTERACT, INTERACT, STAY)
HANDOVER, IDLE = 4, 10


class CookConvention(NamedTuple):
    """A convention as arrays, each with any leading batch shape of the observations' rows: goal scores [K]; what a
    goal off the cook's role loses while its own work waits [2, K] and the goals that are its own work (bool [2, K]),
    each as the first cook of the two and as the second, which differ for a convention that splits the work (the
    first by position, west of its partner or north where they share a column; or, with `by_seat`, the cook in seat
    0); the move order (int [4], indices of NORTH, SOUTH, EAST, WEST); the goal and move temperatures, noise,
    whether it prefers hand-overs, whether it keeps to its role when none of its own work can be done and whether
    its split goes by seat (scalars)."""

    scores: jax.Array
    off_role: jax.Array
    own_work: jax.Array
    move_order: jax.Array
    goal_temperature: jax.Array
    move_temperature: jax.Array
    noise: jax.Array
    prefer_handover: jax.Array
    strict_role: jax.Array
    by_seat: jax.Array


def _shift(grid: jax.Array, dx: int, dy: int, fill) -> jax.Array:
    """[..., H, W]: each cell's neighbour at (x + dx, y + dy), `fill` outside the grid."""
    height, width = grid.shape[-2:]
    pad = [(0, 0)] * (grid.ndim - 2) + [(1, 1), (1, 1)]
    padded = jnp.pad(grid, pad, constant_values=fill)
    return padded[..., 1 + dy: 1 + dy + height, 1 + dx: 1 + dx + width]


DIRECTIONS = ((0, -1), (0, 1), (1, 0), (-1, 0))  # NORTH, SOUTH, EAST, WEST as (dx, dy)


def _neighbours(grid: jax.Array, fill) -> jax.Array:
    """[..., H, W] -> [..., 4, H, W]: the neighbour of every cell in each move's direction."""
    return jnp.stack([_shift(grid, dx, dy, fill) for dx, dy in DIRECTIONS], axis=-3)


def _moved(grid: jax.Array) -> jax.Array:
    """bool [..., H, W] -> [..., 4, H, W]: the cells one step in each direction from each True cell."""
    return jnp.stack([_shift(grid, -dx, -dy, False) for dx, dy in DIRECTIONS], axis=-3)


def _beside(targets: jax.Array) -> jax.Array:
    """bool [..., H, W]: the cells with a target among their four neighbours."""
    return _neighbours(targets, False).any(-3)


def distance_from(sources: jax.Array, walkable: jax.Array) -> jax.Array:
    """float [..., H, W]: steps over walkable cells from the nearest walkable source cell (`UNREACHABLE` where none
    can be reached); a breadth-first wave of one step per iteration, until no distance changes (at most as many
    iterations as the kitchen has cells: the longest path is shorter)."""
    distance = jnp.where(sources & walkable, 0.0, UNREACHABLE)

    def wave(state):
        distance, _, count = state
        closer = _neighbours(distance, UNREACHABLE).min(-3) + 1
        updated = jnp.where(walkable, jnp.minimum(distance, closer), UNREACHABLE)
        return updated, jnp.any(updated != distance), count + 1

    limit = walkable.shape[-1] * walkable.shape[-2]
    distance, _, _ = jax.lax.while_loop(lambda state: state[1] & (state[2] < limit), wave,
                                        (distance, jnp.bool_(True), 0))
    return distance


RANKS = {"scores": 1, "off_role": 2, "own_work": 2, "move_order": 1}  # a field's dims beyond the rows' (else 0)


def per_row(convention: CookConvention, n: int) -> CookConvention:
    """The convention's arrays with a leading dim of n rows: one convention for every row, or one per row."""
    def rows(name, leaf):
        rank = RANKS.get(name, 0)
        return jnp.broadcast_to(jnp.asarray(leaf), (n, *jnp.shape(leaf)[jnp.ndim(leaf) - rank:]))

    return CookConvention(*(rows(name, leaf) for name, leaf in zip(CookConvention._fields, convention)))


def by_side(convention: CookConvention, me: jax.Array, partner: jax.Array, seats: jax.Array) -> CookConvention:
    """Rows [N] of a convention with its role arrays [N, K] as each cook's side makes them: the first of the two by
    position (west of its partner, north where they share a column; bool [N, H, W] cells), or by seat (int [N]) for
    a convention whose split goes `by_seat`, plays the first row."""
    height, width = me.shape[-2:]

    def place(cells):  # column-major order: west before east, then north before south
        index = cells.reshape(cells.shape[0], -1).argmax(-1)
        return (index % width) * height + index // width

    second = jnp.where(convention.by_seat, seats == 1, place(me) > place(partner))[:, None]
    return convention._replace(off_role=jnp.where(second, convention.off_role[:, 1], convention.off_role[:, 0]),
                               own_work=jnp.where(second, convention.own_work[:, 1], convention.own_work[:, 0]))


def walkable_floor(observation: jax.Array) -> jax.Array:
    """bool [N, H, W]: the cells a cook may walk (the cooks count only where they stand in the way); items lie only
    on counters, so it never changes during an episode."""
    present = observation > 0
    loose = ~(present[..., Channel.SELF] | present[..., Channel.PARTNER])
    fixed = (Channel.POT, Channel.EMPTY_COUNTER, Channel.ONION_PILE, Channel.PLATE_PILE, Channel.GOAL)
    items = present[..., Channel.SOUP] | present[..., Channel.PLATE] | present[..., Channel.ONION]
    return ~(jnp.any(present[..., jnp.array(fixed)], axis=-1) | (items & loose))


def floor_tables(walkable: jax.Array) -> jax.Array:
    """float [N, H * W, H * W]: steps from every cell (row) to every cell over each kitchen's floor (`UNREACHABLE`
    from or to a cell off it); computed once per episode and passed to `cook_logits`, the cook reads rows of it
    instead of running its waves from its own and its partner's cells every step."""
    n, height, width = walkable.shape
    cells = height * width
    starts = jnp.eye(cells, dtype=jnp.bool_).reshape(1, cells, height, width)
    return distance_from(starts, walkable[:, None]).reshape(n, cells, cells)


def _rows(tables: jax.Array, plan: jax.Array | None, cells: jax.Array) -> jax.Array:
    """float [N, ..., H * W]: the steps from the cell of each mask cells bool [N, ..., H, W] (one cell at most) to
    every cell, read off the tables (a row's own, or its `plan`'s of tables shared by kitchens of one floor plan);
    `UNREACHABLE` where a mask is empty."""
    flat = cells.reshape(*cells.shape[:-2], -1)
    index = flat.argmax(-1).reshape(cells.shape[0], -1)  # [N, M]
    cells_count = tables.shape[-1]
    row = index + (jnp.arange(cells.shape[0]) if plan is None else plan)[:, None] * cells_count
    rows = tables.reshape(-1, cells_count)[row]  # [N, M, H * W]
    return jnp.where(flat.any(-1, keepdims=True), rows.reshape(flat.shape), UNREACHABLE)


def cook_logits(observation: jax.Array, convention: CookConvention, tables: jax.Array | None = None,
                plan: jax.Array | None = None, detour_rows: int | None = None,
                seats: jax.Array | None = None) -> jax.Array:
    """uint8 observations [N, H, W, 26] (one seat's view a row) -> logits [N, 6] of the scripted cook of each row's
    `convention` (arrays with leading dim N, or unbatched for one convention); the likeliest action's logit is 0.
    `tables`: the rows' `floor_tables` [N, ...], where the caller keeps them through the episode, or with `plan`
    (int [N]) tables [P, ...] of the floor plans the rows index (else the waves run here). `detour_rows` (static): the
    waves around a partner in the way run for that many rows at most, those that meet their partner, where no more
    of them do (a CPU's saving: the choice is a branch the host reads, so None, every row's, on a GPU). `seats`
    (int [N]): the seat each row's cook plays, for a convention whose split goes by seat (None: the rows alternate
    seats 0 and 1, as [..., 2] seats' views flattened)."""
    n = observation.shape[0]
    obs = observation.astype(jnp.float32)
    present = obs > 0
    me, partner = present[..., Channel.SELF], present[..., Channel.PARTNER]
    seats = jnp.arange(n) % 2 if seats is None else seats
    conv = by_side(per_row(convention, n), me, partner, seats)
    walkable = walkable_floor(observation)

    def distances(cells):  # [N, ..., H, W] of one cell each -> steps from it to every cell [N, ..., H * W]
        if tables is not None:
            return _rows(tables, plan, cells)
        return distance_from(cells, walkable.reshape(n, *[1] * (cells.ndim - 3), *walkable.shape[1:])).reshape(
            *cells.shape[:-2], -1)

    from_partner = distances(partner).reshape(partner.shape)  # [N, H, W]
    targets, partner_empty = _goal_tiles(present, obs, from_partner)
    steps, detours, ends = _goal_steps(me, partner, walkable, targets, distances, detour_rows)
    goal_weights, reachable = _goal_weights(conv, steps, ends, partner_empty, from_partner.reshape(n, -1))
    chances = _move_chances(conv, obs, me, partner, targets, steps, detours, reachable)
    probs = (goal_weights[..., None] * chances).sum(1)
    probs = jnp.where(goal_weights.sum(1, keepdims=True) > 0, probs, 1.0 / NUM_ACTIONS)
    noise = conv.noise[:, None]
    probs = jnp.where(noise > 0, (1 - noise) * probs + noise / NUM_ACTIONS, probs)
    safe = jnp.where(probs > 0, probs, 1.0)
    return jnp.where(probs > 0, jnp.log(safe) - jnp.log(probs.max(-1, keepdims=True)), -1e9)


def _goal_tiles(present: jax.Array, obs: jax.Array, from_partner: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The tiles each goal of the goal list heads for, given what the cook holds and what the kitchen wants
    ([N, K, H, W]; none where the goal does not apply), and whether the partner's hands are empty [N]."""

    def channel(c):
        return present[..., c]

    me, partner = channel(Channel.SELF), channel(Channel.PARTNER)
    loose = ~(me | partner)
    pot = channel(Channel.POT)
    ready_pot = pot & channel(Channel.SOUP)
    cooking_pot = pot & channel(Channel.COOKING_OR_SOUP)
    open_pot = pot & ~channel(Channel.COOKING_OR_SOUP) & (obs[..., Channel.ONIONS_IN_POT] < 3)
    soup_on_counter = channel(Channel.SOUP) & ~pot & loose
    plates = channel(Channel.PLATE_PILE) | (channel(Channel.PLATE) & loose)
    onions = channel(Channel.ONION_PILE) | (channel(Channel.ONION) & loose)
    partner_side = partner | (from_partner < UNREACHABLE)
    handover = channel(Channel.EMPTY_COUNTER) & _beside(partner_side)

    def held(item, who=me):
        return (channel(item) & who).any((1, 2))

    partner_empty = ~(held(Channel.PLATE, partner) | held(Channel.SOUP, partner) | held(Channel.ONION, partner))
    partner_has_plate = ((channel(Channel.PLATE) | channel(Channel.SOUP)) & partner).any((1, 2))
    plate_wanted = cooking_pot.any((1, 2)) & ~partner_has_plate
    onion_wanted = open_pot.any((1, 2))

    def when(condition, targets):
        return targets & condition[:, None, None]

    holding_soup, holding_onion, holding_plate = held(Channel.SOUP), held(Channel.ONION), held(Channel.PLATE)
    empty = ~(holding_soup | holding_onion | holding_plate)
    return jnp.stack([
        when(holding_soup, channel(Channel.GOAL)),
        when(holding_onion, open_pot),
        when(holding_plate, ready_pot),
        when(holding_plate, cooking_pot & ~ready_pot),
        when(~empty, handover),
        when(empty, soup_on_counter),
        when(empty & plate_wanted, plates),
        when(empty & onion_wanted, onions),
        when(empty, plates),
        when(empty, onions),
        jnp.zeros_like(pot),  # idling needs no tile
    ], axis=1), partner_empty  # fmt: skip


def _goal_steps(me: jax.Array, partner: jax.Array, walkable: jax.Array, targets: jax.Array, distances,
                detour_rows: int | None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Steps to every goal [N, K, 5] from the cook's cell and each cell around it, over the floor (`steps`), and
    with the partner's cell closed (`detours`: a way around it, used where the partner stands beside the cook);
    and the cells beside each goal's tiles [N, K, H * W]."""
    n, k = targets.shape[:2]
    starts = jnp.concatenate([me[:, None], _moved(me)], axis=1)  # [N, 5, H, W]
    ends = (walkable[:, None] & _beside(targets)).reshape(n, k, -1)  # [N, K, H * W]

    def nearest(steps_from):  # [N, 5, H * W] -> [N, K, 5]
        return jnp.where(ends[:, :, None], steps_from[:, None], UNREACHABLE).min(-1)

    steps = nearest(distances(starts))
    beside_partner = (starts[:, 1:] & partner[:, None]).any((1, 2, 3))
    open_floor = walkable & ~partner

    def every_row(_):
        around = distance_from(starts, open_floor[:, None]).reshape(n, 5, -1)
        return jnp.where(beside_partner[:, None, None], nearest(around), steps)

    def those_rows(_):  # the rows beside their partner, gathered, their waves run, put back
        rows = jnp.nonzero(beside_partner, size=detour_rows, fill_value=n)[0]
        kept = jnp.minimum(rows, n - 1)
        around = distance_from(starts[kept], open_floor[kept][:, None]).reshape(len(rows), 5, -1)
        found = jnp.where(ends[kept][:, :, None], around[:, None], UNREACHABLE).min(-1)
        return steps.at[rows].set(found, mode="drop")

    if detour_rows is None:
        detours = every_row(None)
    else:
        detours = jax.lax.cond(beside_partner.sum() <= detour_rows, those_rows, every_row, None)
    return steps, detours, ends


def _goal_weights(conv: CookConvention, steps: jax.Array, ends: jax.Array, partner_empty: jax.Array,
                  from_partner: jax.Array) -> tuple[jax.Array, jax.Array]:
    """How much the cook heads for each goal [N, K] by its convention (scores, role, temperature, hand-overs), over
    the goals it can reach; and which it can reach [N, K]."""
    n, k = steps.shape[:2]
    here = steps[..., 0]
    reachable = (here < UNREACHABLE).at[:, IDLE].set(True)
    busy = (reachable & conv.own_work).any(1, keepdims=True) | conv.strict_role[:, None]
    scores = jnp.where(reachable, conv.scores - busy * conv.off_role, -jnp.inf)
    hot = conv.goal_temperature[:, None] > 0
    tempered = jax.nn.softmax(scores / jnp.where(hot, conv.goal_temperature[:, None], 1.0), axis=1)
    goal_weights = jnp.where(hot, tempered, jax.nn.one_hot(scores.argmax(1), k))
    goal_weights = jnp.where(jnp.isinf(scores).all(1, keepdims=True), 0.0, goal_weights)
    goal_weights = jnp.where(conv.prefer_handover[:, None],
                             _prefer_handover(goal_weights, here, reachable, ends, partner_empty, from_partner),
                             goal_weights)
    return goal_weights, reachable


def _first_downhill(order: jax.Array, here: jax.Array, next_cells: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[N, K]: the first move in the cook's `order` that gets nearer, and whether there is one."""
    downhill = next_cells == here[..., None] - 1
    in_order = jnp.take_along_axis(downhill, jnp.broadcast_to(order[:, None], downhill.shape), axis=-1)
    return jnp.take_along_axis(order, in_order.argmax(-1), axis=1), (here < UNREACHABLE) & downhill.any(-1)


def _move_chances(conv: CookConvention, obs: jax.Array, me: jax.Array, partner: jax.Array, targets: jax.Array,
                  steps: jax.Array, detours: jax.Array, reachable: jax.Array) -> jax.Array:
    """Per goal, the chances of each action [N, K, 6]: the first move downhill in the cook's order, or on arrival
    turning to the tile and acting; yielding to a partner in the way or contesting its cell, around it where a
    detour exists; spread by the convention's move temperature."""
    n, k = steps.shape[:2]
    here, next_cells = steps[..., 0], steps[..., 1:]

    def around_me(grid):  # [N, 4]: the four cells around each cook, in the order of the moves
        return (_neighbours(grid.astype(jnp.float32), 0.0) * me[:, None]).sum((-2, -1))

    step, _ = _first_downhill(conv.move_order, here, next_cells)
    tiles_around = jnp.einsum("nkc,ndc->nkd", targets.reshape(n, k, -1).astype(jnp.float32),
                              _moved(me).reshape(n, 4, -1).astype(jnp.float32))
    tile = tiles_around.argmax(-1)
    facing = (obs[..., Channel.SELF_FACING:Channel.SELF_FACING + 4] * me[..., None]).sum((1, 2)).argmax(1)
    arrived = reachable & (here == 0)
    on_arrival = jnp.broadcast_to(jnp.array(ON_ARRIVAL), (n, k))
    action = jnp.where(arrived, jnp.where(facing[:, None] == tile, on_arrival, tile), step).at[:, IDLE].set(STAY)
    ahead = jnp.take_along_axis(around_me(partner), step, axis=1) > 0
    contested = ~arrived & ~ahead & (jnp.take_along_axis(around_me(partner | _beside(partner)), step, axis=1) > 0)
    blocked_way = ~arrived & ahead
    detour, has_detour = _first_downhill(conv.move_order, detours[..., 0], detours[..., 1:])
    detour = jnp.where(blocked_way, detour, action)

    def one_hot(actions):
        return jax.nn.one_hot(actions, NUM_ACTIONS, dtype=jnp.bool_)

    moving = (~arrived).at[:, IDLE].set(False)
    allowed = one_hot(action)
    yielding = (contested | (blocked_way & has_detour)) & moving
    allowed = jnp.where(yielding[..., None], one_hot(detour) | one_hot(jnp.full_like(action, STAY)), allowed)
    allowed = allowed | (blocked_way & ~has_detour & moving)[..., None]
    chances = allowed.astype(jnp.float32) / allowed.sum(-1, keepdims=True)
    return jnp.where((moving & reachable & (conv.move_temperature[:, None] > 0))[..., None],
                     _boltzmann_moves(detours, chances, conv.move_temperature), chances)


def _boltzmann_moves(steps_around: jax.Array, planned: jax.Array, temperature: jax.Array) -> jax.Array:
    """[N, K, 6]: moves drawn by the steps left after each, a wait where no move is open."""
    here, after = steps_around[..., :1], steps_around[..., 1:]
    open_moves = after < UNREACHABLE
    hot = jnp.where(temperature > 0, temperature, 1.0)[:, None, None]
    logits = jnp.where(open_moves, -(after - here) / hot, -jnp.inf)
    moves = jax.nn.softmax(jnp.where(open_moves.any(-1, keepdims=True), logits, 0.0), -1)
    chances = jnp.concatenate([moves, jnp.zeros_like(planned[..., 4:])], -1)
    return jnp.where(open_moves.any(-1, keepdims=True), chances, planned)


def _prefer_handover(goal_weights, here, reachable, ends, partner_empty, from_partner):
    """A cook that prefers hand-overs puts its item on a counter the partner can reach where the partner's hands are
    empty and the partner stands nearer the goal the cook carries it to."""
    partner_steps = jnp.where(ends, from_partner[:, None], UNREACHABLE).min(-1)
    carried = goal_weights[:, :HANDOVER].argmax(1, keepdims=True)
    carrying = goal_weights[:, :HANDOVER].sum(1) > 0
    nearer = (jnp.take_along_axis(partner_steps, carried, 1)[:, 0] + 1
              < jnp.take_along_axis(here, carried, 1)[:, 0])
    hand_over = carrying & nearer & partner_empty & reachable[:, HANDOVER]
    return jnp.where(hand_over[:, None], jax.nn.one_hot(jnp.full_like(carried[:, 0], HANDOVER), goal_weights.shape[1]),
                     goal_weights)
