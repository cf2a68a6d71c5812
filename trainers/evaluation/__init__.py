"""Self-play and cross-play evaluation of trained teams: the paper's matrices, tables, figures and GIFs.

    kitchen-eval configs/eval/paper.yaml                     # the paper's protocol
    kitchen-eval configs/eval/paper.yaml rollouts=5 heldout=10 out_dir=results/quick

A *population* is a set of conditions (e.g. "ippo_mlp_ik"), each a list of trained teams (its seeds). Every ordered pair
(agent 0 of team i, agent 1 of team j) within a condition plays: self-play (SP) when i == j, cross-play (XP) otherwise;
so does every pair across the conditions named in `cross`. Each pair plays `rollouts` episodes on every test grid: the 5
expanded classic layouts and the held-out generated levels. With `partner` on, every team also plays with the scripted
cook (`torch_kitchen.partners.scripted_cook`), a partner outside every training population, in both seats; the cook's
own self-play is the reference row.

All pairs x grids x rollouts run as batches of up to `max_envs` kitchens through the rollout routine that
training uses (`trainers.ppo.collection`): kitchen b of a batch is pinned to grid b % G, and a `SeatedPolicy` gives
each kitchen's two seats to the teams of its pair. Actions are sampled, recurrent teams carry their state. Batch b
plays with seed + b, so `workers` processes share the batches and give the numbers of one.

The modules, by concern (their public names are all importable from `trainers.evaluation`):

    teams      a trained team (`Team`, `load_team`), a population of them, the scripted cook as a team
    pairs      the pairs (`make_matchups`), the test grids (`evaluation_grids`), playing them (`play`)
    partners   partners from outside the population: the human proxies of the test grids
    tables     per-pair rows, the summary per condition and grid group, CSV and markdown
    gifs       GIFs of single episodes
    command    the whole job (`evaluate`), the report of a finished run, the command line `kitchen-eval`
"""

from trainers.evaluation.command import evaluate, main, report_trained_team
from trainers.evaluation.gifs import parse_gif_request, record_gif
from trainers.evaluation.pairs import (
    CROSS,
    HUMAN,
    PARTNER,
    SP,
    XP,
    Batches,
    BatchPlayer,
    Matchup,
    Outcomes,
    cross_condition,
    evaluation_grids,
    is_heldout,
    make_matchups,
    play,
)
from trainers.evaluation.strangers import load_human_proxies, with_human_proxies
from trainers.evaluation.tables import (
    at_home,
    grid_groups,
    markdown_summary,
    mean_and_stderr,
    pair_rows,
    pair_scores,
    summary_rows,
    visit_shares,
    write_csv,
)
from trainers.evaluation.teams import (
    HUMAN_PROXY_RUN,
    SCRIPTED_CONDITION,
    Team,
    load_population,
    load_team,
    scripted_cook_team,
)

__all__ = [
    "CROSS", "HUMAN", "HUMAN_PROXY_RUN", "PARTNER", "SCRIPTED_CONDITION", "SP", "XP",
    "BatchPlayer", "Batches", "Matchup", "Outcomes", "Team",
    "at_home", "cross_condition", "evaluate", "evaluation_grids", "grid_groups", "is_heldout", "load_human_proxies",
    "load_population", "load_team", "main", "make_matchups", "markdown_summary", "mean_and_stderr", "pair_rows",
    "pair_scores", "parse_gif_request", "play", "record_gif", "report_trained_team", "scripted_cook_team",
    "summary_rows", "visit_shares", "with_human_proxies", "write_csv",
]
