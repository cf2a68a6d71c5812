"""The Infinite Kitchen level generator: random solvable 7x7 kitchens (or 9x9: `GeneratorConfig.size`, a share of
them 7x7 kitchens drawn inside: `p_smaller`), in pure JAX.

Every level is a border of counters around a 5x5 interior (7x7 at size 9; the numbers below are those of 7x7,
their 9x9 counterparts in `Geometry`: middle row and column 4, walls of 7 interior cells, 8-cell quadrants).
`sample_level` draws, with independent keys:

1. Interior walls by one of four predicates: none (p_empty), a 3x3 middle block whose 9 cells are each
   reopened with p_block_reopen (p_middle), or a continuous wall down column 3 (p_vertical) or along row 3
   (p_horizontal) that stays whole with p_wall_intact and otherwise has exactly 2 of its 5 interior cells
   reopened.
2. One onion pile, plate pile, pot and goal on 4 distinct SAFE cells: border cells that are neither corners
   nor T-junctions (where a row-3 or column-3 wall meets the border).
3. For each of those 4 kinds, with p_extra_item, a second copy on a QUESTIONABLE cell that is currently a
   wall (the middle cross, the 3x3 block, the corners); the extras take distinct cells. They may be
   unreachable; no task depends on them.
4. A loose onion, plate and dish, each with its own probability, on distinct plain counters.
5. Two agents in diagonally opposite quadrants, one uniform cell in each, a fair coin for which agent goes
   where, uniform facings; hands and pots empty.

Why every level is solvable: every safe cell borders a quadrant cell, and no predicate ever walls a quadrant
cell or cuts a quadrant from the other quadrant on its side of a wall (the interior ring, rows 1 and 5 and
columns 1 and 5, is only ever walled at row 3 or column 3). So each agent reaches every required item on its
side. If a continuous wall separates the agents and all items lie on one side, that side's agent can do the
whole task; if the items are split, the agents pass items over the wall's counters, which face floor on
both sides and are never all taken by extras (5 counters, at most 4 extras), as in Forced Coordination; in
every other case either agent can do the task alone.

Coordinates in this module's constants are (row, col); cells are flat indices `row * 7 + col` like
`State.agent_pos`. The held-out evaluation set (`heldout_levels`, `heldout_grids`) is 100 generated levels
plus the 5 expanded classic layouts; `sample_training_level` rejects any level whose grid is one of them.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jax_env.layouts import COUNTER, EXPANDED_LAYOUTS, FLOOR, GOAL, ONION_PILE, PLATE_PILE, POT, get_layout
from jax_env.state import DISH, ONION, PLATE, POT_EMPTY, State, make_state

SIZES = (7, 9)  # kitchen sizes the construction keeps solvable (a border around a 5x5 or 7x7 interior)
SIZE = 7  # the paper's
NUM_CELLS = SIZE * SIZE

# Required kinds in placement order; extra copies use the same order.
ITEM_KINDS = (ONION_PILE, PLATE_PILE, POT, GOAL)
# Loose item kinds, in the order of `GeneratorConfig.loose_probs`.
LOOSE_KINDS = (ONION, PLATE, DISH)

# Seed of the held-out evaluation set; changing it changes which levels training never sees.
HELDOUT_SEED = 20240
NUM_HELDOUT_GENERATED = 100


@dataclasses.dataclass(frozen=True)
class Geometry:
    """The cells of an S x S kitchen (S odd, m = S // 2 its middle row and column) that the construction names,
    as (row, col) tuples; the module docstring's numbers are those of S = 7 (m = 3)."""

    size: int

    @property
    def middle(self) -> int:
        return self.size // 2

    @property
    def border(self) -> tuple:
        last = self.size - 1
        return tuple((r, c) for r in range(self.size) for c in range(self.size) if r in (0, last) or c in (0, last))

    @property
    def corners(self) -> tuple:
        last = self.size - 1
        return ((0, 0), (0, last), (last, 0), (last, last))

    @property
    def t_junctions(self) -> tuple:
        """Where a middle-row or middle-column wall meets the border."""
        m, last = self.middle, self.size - 1
        return ((0, m), (m, 0), (m, last), (last, m))

    @property
    def safe(self) -> tuple:
        return tuple(cell for cell in self.border if cell not in self.corners + self.t_junctions)

    @property
    def block(self) -> tuple:
        """The 3x3 middle block."""
        m = self.middle
        return tuple((r, c) for r in range(m - 1, m + 2) for c in range(m - 1, m + 2))

    @property
    def vertical(self) -> tuple:
        return tuple((r, self.middle) for r in range(1, self.size - 1))

    @property
    def horizontal(self) -> tuple:
        return tuple((self.middle, c) for c in range(1, self.size - 1))

    @property
    def cross(self) -> tuple:
        m = self.middle
        return tuple(sorted({(m, c) for c in range(self.size)} | {(r, m) for r in range(self.size)}))

    @property
    def questionable(self) -> tuple:
        return tuple(sorted(set(self.cross) | set(self.block) | set(self.corners)))

    @property
    def quadrants(self) -> tuple:
        """Top-left, top-right, bottom-left, bottom-right: the interior cells off the middle row and column and
        off the block, row by row (the bottom-right one's from the bottom row up); no predicate ever walls them."""
        m, last = self.middle, self.size - 1
        rows = (range(1, m), range(1, m), range(m + 1, last), range(last - 1, m, -1))  # the last from the bottom
        cols = (range(1, m), range(m + 1, last), range(1, m), range(m + 1, last))
        return tuple(tuple((r, c) for r in rs for c in cs if (r, c) not in self.block) for rs, cs in zip(rows, cols))

    def flat(self, cells) -> np.ndarray:
        return np.asarray([r * self.size + c for r, c in cells], dtype=np.int32)

    def mask(self, cells) -> np.ndarray:
        mask = np.zeros(self.size * self.size, dtype=bool)
        mask[self.flat(cells)] = True
        return mask


@functools.cache
def geometry(size: int) -> Geometry:
    if size not in SIZES:
        raise ValueError(f"Infinite Kitchen levels are {' or '.join(f'{s}x{s}' for s in SIZES)}, not {size}x{size}")
    return Geometry(size)


# The paper's 7x7 geometry, by name.
BORDER_CELLS = geometry(SIZE).border
CORNER_CELLS = geometry(SIZE).corners
T_JUNCTION_CELLS = geometry(SIZE).t_junctions
SAFE_CELLS = geometry(SIZE).safe
BLOCK_CELLS = geometry(SIZE).block
VERTICAL_CELLS = geometry(SIZE).vertical
HORIZONTAL_CELLS = geometry(SIZE).horizontal
CROSS_CELLS = geometry(SIZE).cross
QUESTIONABLE_CELLS = geometry(SIZE).questionable
QUADRANT_CELLS = geometry(SIZE).quadrants
# The two diagonal quadrant pairs: (top-left, bottom-right) and (top-right, bottom-left).
QUADRANT_PAIRS = ((0, 3), (1, 2))
_QUADRANT_PAIRS = np.asarray(QUADRANT_PAIRS, dtype=np.int32)  # (2, 2)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GeneratorConfig:
    """The kitchen size and probabilities of the Infinite Kitchen generator (defaults: the paper's).

    Hashable, so it can be a static argument (`jax.jit(sample_level, static_argnames="config")`), and a pytree
    of scalars, so it can also be traced: `jax.jit(jax.vmap(sample_level, in_axes=(0, None)))(keys, config)`
    compiles once for every config of one size (the size is static: it decides the arrays' shapes).
    """

    size: int = dataclasses.field(default=SIZE, metadata={"static": True})
    """the kitchens' side, border included: 7 (the paper's) or 9"""
    p_empty: float = 0.1
    """probability of the predicate with no interior walls"""
    p_middle: float = 0.3
    """probability of the 3x3 middle-block predicate"""
    p_vertical: float = 0.3
    """probability of the continuous wall down column 3"""
    p_horizontal: float = 0.3
    """probability of the continuous wall along row 3"""
    p_block_reopen: float = 0.5
    """probability that each middle-block cell is reopened as floor, independently"""
    p_wall_intact: float = 0.25
    """probability that a continuous wall stays whole; otherwise exactly 2 of its 5 interior cells reopen"""
    p_extra_item: float = 0.75
    """probability, per item kind, of a second onion pile / plate pile / pot / goal on a questionable wall"""
    p_loose_onion: float = 0.5
    """probability of a loose onion on a plain counter"""
    p_loose_plate: float = 0.5
    """probability of a loose plate on a plain counter"""
    p_loose_dish: float = 0.5
    """probability of a loose dish (plated soup) on a plain counter"""
    p_smaller: float = dataclasses.field(default=0.0, metadata={"static": True})
    """larger kitchens only: probability that a level is a 7x7 kitchen drawn inside, at a uniform offset, with
    counters around it, as the classic layouts' small rooms are (static: 0 costs nothing)"""

    def __post_init__(self):
        geometry(self.size)  # ValueError for a size the construction does not keep solvable
        probabilities = [field for field in dataclasses.fields(self) if field.name != "size"]
        values = [getattr(self, field.name) for field in probabilities]
        if not all(isinstance(value, (int, float)) for value in values):
            return  # traced or batched fields, rebuilt by jax; checked when first built from numbers
        for field in probabilities:
            # Plain floats, so that configs given with ints and with floats trace alike.
            value = float(getattr(self, field.name))
            object.__setattr__(self, field.name, value)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"GeneratorConfig.{field.name} = {value} is not a probability in [0, 1]")
        if self.size == SIZE and self.p_smaller:
            raise ValueError(f"GeneratorConfig.p_smaller = {self.p_smaller}: {SIZE}x{SIZE} kitchens are the smallest")
        total = sum(self.predicate_probs)
        if abs(total - 1.0) > 1e-6:
            raise ValueError(
                "GeneratorConfig predicate probabilities must sum to 1: "
                f"p_empty + p_middle + p_vertical + p_horizontal = {total}"
            )

    @property
    def predicate_probs(self) -> tuple[float, float, float, float]:
        """(p_empty, p_middle, p_vertical, p_horizontal): the four predicates' probabilities, in this order."""
        return (self.p_empty, self.p_middle, self.p_vertical, self.p_horizontal)

    @property
    def loose_probs(self) -> tuple[float, float, float]:
        """(p_loose_onion, p_loose_plate, p_loose_dish), in the order of LOOSE_KINDS."""
        return (self.p_loose_onion, self.p_loose_plate, self.p_loose_dish)


def _distinct_choice(u: jax.Array, allowed: jax.Array, k: int) -> jax.Array:
    """int32 (k,): k distinct indices drawn uniformly, in random order, among the True ones of `allowed` (bool (n,)).

    u: float32 (>= n,) iid uniforms. The top k of iid uniform scores is a uniformly random ordered k-subset;
    `allowed` must hold >= k entries.
    """
    scores = jnp.where(allowed, u[: allowed.shape[0]], -1.0)
    return jax.lax.top_k(scores, k)[1].astype(jnp.int32)


def _uniform_int(u: jax.Array, n: int) -> jax.Array:
    """int32, shape of u: iid uniform integers in [0, n) from iid uniforms u."""
    return jnp.minimum(jnp.floor(u * n), n - 1).astype(jnp.int32)


def _categorical(u: jax.Array, probs) -> jax.Array:
    """int32 (): index i drawn with probability probs[i] from one uniform u; an index of probability 0 is never
    drawn."""
    probs = jnp.asarray(probs, jnp.float32)
    index = jnp.sum(u >= jnp.cumsum(probs)[:-1]).astype(jnp.int32)
    # Rounding can leave the top threshold just below 1; never step past the last possible index.
    last_possible = jnp.max(jnp.where(probs > 0, jnp.arange(probs.shape[0]), 0))
    return jnp.minimum(index, last_possible)


def _interior_walls(u: jax.Array, config: GeneratorConfig) -> jax.Array:
    """bool (S*S,): interior walls drawn by one of the four predicates; u: float32 (4, >= S - 2) independent
    uniforms."""
    geo = geometry(config.size)
    line = len(geo.vertical)  # interior cells of a continuous wall: 5 at 7x7
    predicate = _categorical(u[0, 0], config.predicate_probs)
    block_kept = u[1, : len(geo.block)] >= config.p_block_reopen
    intact = u[2, 0] < config.p_wall_intact
    reopened = _distinct_choice(u[3], jnp.ones(line, bool), 2)
    line_kept = intact | ~jnp.zeros(line, bool).at[reopened].set(True)

    none = jnp.zeros(config.size * config.size, bool)
    walls = jnp.stack(
        [
            none,
            none.at[geo.flat(geo.block)].set(block_kept),
            none.at[geo.flat(geo.vertical)].set(line_kept),
            none.at[geo.flat(geo.horizontal)].set(line_kept),
        ]
    )
    return walls[predicate]


def sample_level(key: jax.Array, config: GeneratorConfig = GeneratorConfig()) -> State:
    """One random Infinite Kitchen level of `config.size` (S = 7 by default): grid uint8 (S, S), contents uint8
    (S, S) with loose items and empty pots, agent_pos/agent_dir/agent_inv int32 (2,), step int32 (). Jittable and
    vmappable over `key`. With `config.p_smaller`, a 7x7 level drawn inside instead, from keys of its own, so that
    the full-size levels of a key stay those drawn without it."""
    level = _full_size_level(key, config)
    if not config.p_smaller:
        return level
    smaller = _smaller_level(jax.random.fold_in(key, 1), config)
    drawn_smaller = jax.random.uniform(jax.random.fold_in(key, 2)) < config.p_smaller
    return jax.tree_util.tree_map(lambda inside, full: jnp.where(drawn_smaller, inside, full), smaller, level)


def _smaller_level(key: jax.Array, config: GeneratorConfig) -> State:
    """A 7x7 level of `config`'s probabilities inside a `config.size` kitchen of counters, at a uniform offset:
    solvable as the 7x7 level is, since the agents never leave it."""
    inner_key, offset_key = jax.random.split(key)
    inner = _full_size_level(inner_key, dataclasses.replace(config, size=SIZE, p_smaller=0.0))
    row, col = jax.random.randint(offset_key, (2,), 0, config.size - SIZE + 1)
    counters = jnp.full((config.size, config.size), COUNTER, jnp.uint8)
    return inner.replace(
        grid=jax.lax.dynamic_update_slice(counters, inner.grid, (row, col)),
        contents=jax.lax.dynamic_update_slice(jnp.zeros_like(counters), inner.contents, (row, col)),
        agent_pos=((inner.agent_pos // SIZE + row) * config.size + inner.agent_pos % SIZE + col).astype(jnp.int32),
    )


def _full_size_level(key: jax.Array, config: GeneratorConfig) -> State:
    """`sample_level`'s construction at `config.size` itself."""
    geo, num_cells = geometry(config.size), config.size * config.size
    # Every draw has its own key. The draws are vmapped over their keys, in two widths, so that the program
    # holds 2 random kernels instead of 13 (XLA compiles it several times faster); one row per draw.
    keys = jax.random.split(key, 13)
    u = jax.vmap(lambda k: jax.random.uniform(k, (len(geo.safe),)))(keys[:11])  # float32 (11, 16) at 7x7
    cell_u = jax.vmap(lambda k: jax.random.uniform(k, (num_cells,)))(keys[11:])  # float32 (2, 49) at 7x7

    walls = jnp.asarray(geo.mask(geo.border)) | _interior_walls(u[0:4], config)
    grid = jnp.where(walls, COUNTER, FLOOR).astype(jnp.uint8)

    # Required items: a uniform ordered choice of 4 distinct safe cells.
    safe_order = _distinct_choice(u[4], jnp.ones(len(geo.safe), bool), len(ITEM_KINDS))
    grid = grid.at[jnp.asarray(geo.flat(geo.safe))[safe_order]].set(jnp.asarray(ITEM_KINDS, jnp.uint8))

    # Extras: 4 distinct questionable walls drawn together, each kind keeping its cell with p_extra_item.
    # Required items sit on safe cells, never questionable ones, so the extras cannot land on them.
    extra_cells = _distinct_choice(cell_u[0], jnp.asarray(geo.mask(geo.questionable)) & walls, len(ITEM_KINDS))
    has_extra = u[5, : len(ITEM_KINDS)] < config.p_extra_item
    extra_kinds = jnp.where(has_extra, jnp.asarray(ITEM_KINDS, jnp.uint8), grid[extra_cells])
    grid = grid.at[extra_cells].set(extra_kinds)

    # Loose items on distinct plain counters (no pile, pot or goal).
    loose_cells = _distinct_choice(cell_u[1], grid == COUNTER, len(LOOSE_KINDS))
    has_loose = u[6, : len(LOOSE_KINDS)] < jnp.asarray(config.loose_probs, jnp.float32)
    contents = jnp.zeros(num_cells, jnp.uint8)
    contents = contents.at[loose_cells].set(jnp.where(has_loose, jnp.asarray(LOOSE_KINDS, jnp.uint8), 0))
    contents = jnp.where(grid == POT, jnp.uint8(POT_EMPTY), contents)

    # Agents: a diagonal quadrant pair, one cell in each quadrant, a coin for who goes where.
    pair = jnp.asarray(_QUADRANT_PAIRS)[_uniform_int(u[7, 0], len(QUADRANT_PAIRS))]
    quadrant_cells = np.stack([geo.flat(cells) for cells in geo.quadrants])  # (4, 3) at 7x7
    positions = jnp.asarray(quadrant_cells)[pair, _uniform_int(u[8, :2], quadrant_cells.shape[1])]
    swap = u[9, 0] < 0.5
    agent_pos = jnp.where(swap, positions[::-1], positions).astype(jnp.int32)
    agent_dir = _uniform_int(u[10, :2], 4)

    return State(
        grid=grid.reshape(config.size, config.size),
        contents=contents.reshape(config.size, config.size),
        agent_pos=agent_pos,
        agent_dir=agent_dir,
        agent_inv=jnp.zeros(2, jnp.int32),
        step=jnp.zeros((), jnp.int32),
    )


@jax.jit
def sample_levels(keys: jax.Array, config: GeneratorConfig = GeneratorConfig()) -> State:
    """A batch of levels, one per key (keys (N, 2) or (N,) typed): `sample_level` vmapped and jitted, with the
    config traced, so one compilation per batch size serves every config."""
    return jax.vmap(sample_level, in_axes=(0, None))(keys, config)


def _grid_words(grids: jax.Array) -> jax.Array:
    """uint32 (..., W): the S*S grid bytes packed 4 to a word (zero-padded; 13 words at 7x7); grids are equal iff
    their words are."""
    cells = grids.shape[-2] * grids.shape[-1]
    words = -(-cells // 4)
    flat = jnp.asarray(grids, jnp.uint8).reshape(grids.shape[:-2] + (cells,))
    padded = jnp.pad(flat, [(0, 0)] * (flat.ndim - 1) + [(0, 4 * words - cells)])
    return jax.lax.bitcast_convert_type(padded.reshape(padded.shape[:-1] + (words, 4)), jnp.uint32)


def _sorted_words(grids: jax.Array) -> jax.Array:
    """uint32 (K, W): the grids' words in lexicographic order, for `_contains`."""
    words = _grid_words(grids)
    return words[jnp.lexsort(words.T[::-1])]  # lexsort's last key is its primary one


def _contains(sorted_words: jax.Array, words: jax.Array) -> jax.Array:
    """bool (): whether `words` (uint32 (W,)) is a row of `sorted_words` (uint32 (K, W), sorted). A binary
    search, so that a large held-out set costs log2(K) row comparisons per draw rather than K."""
    num = sorted_words.shape[0]
    if num == 0:
        return jnp.zeros((), bool)

    def less(row):
        differs = row != words
        first = jnp.argmax(differs)
        return differs[first] & (row[first] < words[first])

    def halve(_, bounds):  # keep the first row >= words inside [lo, hi]
        lo, hi = bounds
        mid = (lo + hi) // 2
        go_right = less(sorted_words[mid])
        active = lo < hi
        return jnp.where(active & go_right, mid + 1, lo), jnp.where(active & ~go_right, mid, hi)

    lo, _ = jax.lax.fori_loop(0, num.bit_length(), halve, (jnp.int32(0), jnp.int32(num)))
    return (lo < num) & jnp.all(sorted_words[jnp.minimum(lo, num - 1)] == words)


def is_heldout(grid: jax.Array, heldout: jax.Array) -> jax.Array:
    """bool (): whether `grid` (uint8 (S, S)) equals one of `heldout` (uint8 (K, S, S))."""
    return _contains(_sorted_words(heldout), _grid_words(grid))


def sample_training_level(key: jax.Array, config: GeneratorConfig, heldout: jax.Array) -> State:
    """A level from `sample_level` whose grid is none of `heldout` (uint8 (K, 7, 7)), by rejection: redraws
    with a fresh key until no held-out grid matches. Jittable and vmappable over `key`
    (`jax.vmap(sample_training_level, in_axes=(0, None, None))`)."""
    heldout_words = _sorted_words(heldout)

    def draw(key):
        key, sub = jax.random.split(key)
        level = sample_level(sub, config)
        return key, level, _contains(heldout_words, _grid_words(level.grid))

    _, level, _ = jax.lax.while_loop(lambda carry: carry[2], lambda carry: draw(carry[0]), draw(key))
    return level


@jax.jit
def sample_training_levels(keys: jax.Array, config: GeneratorConfig, heldout: jax.Array) -> State:
    """A batch of training levels, one per key: `sample_training_level` vmapped and jitted."""
    return jax.vmap(sample_training_level, in_axes=(0, None, None))(keys, config, heldout)


@functools.lru_cache(maxsize=8)
def _heldout_levels_np(config: GeneratorConfig) -> State:
    expanded = {layout.grid.tobytes() for layout in _expanded_layouts(config.size)}
    seen: set[bytes] = set()
    kept: list[State] = []
    # The first batch is split(PRNGKey(HELDOUT_SEED), 100); a grid already taken (or equal to an expanded
    # classic layout) is skipped and the shortfall filled from further batches, split(fold_in(seed, round)).
    base = jax.random.PRNGKey(HELDOUT_SEED)
    round_ = 0
    while len(kept) < NUM_HELDOUT_GENERATED:
        keys = jax.random.split(base if round_ == 0 else jax.random.fold_in(base, round_), NUM_HELDOUT_GENERATED)
        batch = jax.tree_util.tree_map(np.asarray, sample_levels(keys, config))
        for i in range(NUM_HELDOUT_GENERATED):
            grid_bytes = batch.grid[i].tobytes()
            if grid_bytes in seen or grid_bytes in expanded or len(kept) == NUM_HELDOUT_GENERATED:
                continue
            seen.add(grid_bytes)
            kept.append(jax.tree_util.tree_map(lambda leaf: leaf[i], batch))
        round_ += 1
    return jax.tree_util.tree_map(lambda *leaves: np.stack(leaves), *kept)


def _expanded_layouts(size: int) -> list:
    """The classic layouts drawn inside kitchens of `size` that the held-out set holds: the 5 expanded ones at
    7x7 (`EXPANDED_LAYOUTS`); none yet at other sizes."""
    return [get_layout(name) for name in EXPANDED_LAYOUTS] if size == SIZE else []


def heldout_levels(config: GeneratorConfig = GeneratorConfig()) -> State:
    """The 100 held-out generated levels of `config.size`, batched: grid uint8 (100, S, S), ... Deterministic
    (HELDOUT_SEED); their grids are distinct from each other and from the expanded classic layouts."""
    # Drawn by the construction's own probabilities, full size, whatever mix of kitchens training draws: one
    # held-out set per size, which training under any probabilities rejects.
    return jax.tree_util.tree_map(jnp.asarray, _heldout_levels_np(GeneratorConfig(size=config.size)))


def heldout_set(config: GeneratorConfig = GeneratorConfig()) -> State:
    """All held-out evaluation levels of `config.size` as start states, batched: the 100 generated levels, then,
    at 7x7, the 5 expanded classic layouts (in `EXPANDED_LAYOUTS` order, agents at their start cells): 105."""
    generated = heldout_levels(config)
    classic = [make_state(layout) for layout in _expanded_layouts(config.size)]
    if not classic:
        return generated
    return jax.tree_util.tree_map(
        lambda generated, *fixed: jnp.concatenate([generated, jnp.stack(fixed)]), generated, *classic
    )


def heldout_grids(config: GeneratorConfig = GeneratorConfig()) -> jax.Array:
    """uint8 (K, S, S): the grids of `heldout_set` (105 at 7x7, 100 at 9x9), which training never samples."""
    return heldout_set(config).grid
