"""`kitchen-study`: a human study from its config to its report.

    kitchen-study check configs/study/example.yaml     # the config checked, the first participants' orders shown
    kitchen-study run configs/study/example.yaml       # serves the study; prints the participants' and operator's links
    kitchen-study analyse studies/example              # the report: STUDY_DIR/analysis/report.md
    kitchen-study power studies/example                # participants needed: STUDY_DIR/analysis/power.md
    kitchen-study simulate configs/study/example.yaml --participants 8   # a pilot by proxies: studies/example-simulated
"""

from __future__ import annotations

import argparse
import logging
import socket
import sys
from pathlib import Path

from web_apps.play.server import AddressError, listening_socket, serve, served_hosts
from web_apps.study.assignment import assign, design_counts
from web_apps.study.config import StudyError, load_study, study_partners
from web_apps.study.power import SIZES

PROG = "kitchen-study"


def error(message: str, status: int = 2) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return status


def check(args) -> int:
    config = load_study(args.config)
    block = config.block_size
    participants = args.participants or block
    print(f"{args.config}: {len(config.conditions)} conditions ({', '.join(config.conditions)}), "
          f"{len(config.kitchens)} kitchens, {config.practice_games} practice + {config.games} games per participant; "
          f"balanced over every {block} participants; the study's folder: {config.folder}/")
    for number in range(participants):
        games = [f"{slot.condition} on {slot.kitchen}" for slot in assign(config, number) if not slot.practice]
        print(f"  participant {number}: {', '.join(games)}")
    for table, counts in design_counts(config, participants).items():
        print(f"games per {table} over the {participants} participants:")
        rows = list(dict.fromkeys(key[0] for key in counts))
        columns = list(dict.fromkeys(key[1] for key in counts))
        width, first = max(4, *map(len, columns)), max(map(len, rows))
        print("  " + " " * first + "".join(f" {column:>{width}}" for column in columns))
        for row in rows:
            print(f"  {row:{first}}" + "".join(f" {counts.get((row, column), 0):{width}d}" for column in columns))
    if participants % block:
        print(f"{participants} participants fill no whole number of blocks of {block}: the counts above are unequal")
    return 0


def study_listener(args) -> socket.socket:
    """The socket a study serves on: the inherited one of --fd, or one listening on --host and --port."""
    if args.fd is None:
        return listening_socket(args.host, args.port)
    try:
        return socket.socket(fileno=args.fd)
    except OSError as failure:
        raise AddressError(f"--fd {args.fd}: {failure.strerror}") from None


def run(args) -> int:
    from web_apps.study.server import create_study_app, open_study, warm_up

    config = load_study(args.config, check=False)
    try:
        partners = study_partners(config)  # the check, and the partners the server's games share
    except StudyError as failure:
        raise StudyError(f"{args.config}: {failure}") from None
    try:
        import uvicorn  # noqa: F401
    except ImportError:
        return error("kitchen-study needs the play extra: pip install .[play]")
    try:  # the address is taken before the warm-up, so that nothing else takes it meanwhile
        listener = study_listener(args)
    except AddressError as busy:
        return error(str(busy))
    host, port = listener.getsockname()[:2]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")  # before the restart's line
    print(f"{PROG}: warming every kitchen and partner up, so that no participant waits for a compilation ...",
          flush=True)
    games, seconds = warm_up(config, partners)
    print(f"{PROG}: {games} kitchen and partner pairs warmed up in {seconds:.1f} s", flush=True)
    database, token, operator = open_study(config, args.token)
    app = create_study_app(config, database, token, operator, served_hosts(host, port, args.allow_host), partners)
    base = f"http://{host}:{port}"
    print(f"{PROG}: study {config.name} in {config.folder}/\n"
          f"  participants: {base}/?token={token}&{config.participant_param}=<their id>\n"
          f"  operator:     {base}/operator?token={token}&key={operator}", flush=True)
    # On SIGTERM or SIGINT every game's socket is closed, which ends its game as cut (played again on return).
    serve(app, listener)
    database.close()
    return 0


def power(args) -> int:
    from web_apps.study.analysis import study_config_of
    from web_apps.study.power import write_power

    folder = Path(args.study_dir)
    path, _ = write_power(study_config_of(folder), folder, args.studies, args.alpha, tuple(args.sizes))
    print(path.read_text())
    print(f"wrote {path} and {path.with_suffix('.png')}")
    return 0


def simulate(args) -> int:
    for option, value in (("--participants", args.participants), ("--parallel", args.parallel),
                          ("--max-steps", args.max_steps or 1)):
        if value < 1:
            return error(f"{option} must be 1 or more, got {value}")
    from web_apps.study.simulate import SimulationError, run_pilot

    try:
        return run_pilot(args.config, args.participants, args.out, args.seed, args.proxy, args.stand_in,
                         args.parallel, args.keep_pace, args.max_steps)
    except SimulationError as failure:
        return error(str(failure), 1)


def analyse(args) -> int:
    from web_apps.study.analysis import analyse as write

    report = write(args.study_dir)
    print(f"{PROG}: the report is {report} (with games.csv, answers.csv and deliveries.png beside it)")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    checking = commands.add_parser("check", help="check a study config and show the first participants' orders")
    checking.add_argument("config")
    checking.add_argument("--participants", type=int, default=0,
                          help="the first N participants' games and the design's counts over them (default: a block)")
    checking.set_defaults(handle=check)
    serving = commands.add_parser("run", help="serve a study (resumes it where it stopped)")
    serving.add_argument("config")
    serving.add_argument("--host", default="127.0.0.1")
    serving.add_argument("--port", type=int, default=8000, help="0: any free port (the links say which)")
    serving.add_argument("--fd", type=int, metavar="FD",
                         help="serve on this inherited listening socket instead of --host and --port (a process "
                              "that starts the server, e.g. kitchen-study simulate, owns the address)")
    serving.add_argument("--token", help="the participants' key in the link (default: the study's own, made once)")
    serving.add_argument("--allow-host", action="append", default=[], metavar="HOST[:PORT]",
                         help="another Host header to answer to (the study behind a proxy or a public name)")
    serving.set_defaults(handle=run)
    analysing = commands.add_parser("analyse", help="write a study's report from its database and records")
    analysing.add_argument("study_dir")
    analysing.set_defaults(handle=analyse)
    sizing = commands.add_parser("power", help="how many participants: power by simulation from a study's games")
    sizing.add_argument("study_dir")
    sizing.add_argument("--studies", type=int, default=200, help="simulated studies per number of participants")
    sizing.add_argument("--alpha", type=float, default=0.05)
    sizing.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="numbers of participants simulated")
    sizing.set_defaults(handle=power)
    simulating = commands.add_parser("simulate", help="a pilot by proxies: simulated participants through the "
                                                      "study's server, into a study folder")
    simulating.add_argument("config")
    simulating.add_argument("--participants", type=int, required=True, metavar="N",
                            help="simulated participants, 1 or more")
    simulating.add_argument("--out", metavar="STUDY_DIR",
                            help="the simulated study's folder (default: the study's folder's name with -simulated)")
    simulating.add_argument("--seed", type=int, default=0,
                            help="draws each participant's noise, leaning, stand-in, keys and answers")
    simulating.add_argument("--proxy", metavar="RUN",
                            help="the human proxy of each kitchen ({kitchen}: its name; default: "
                                 "runs/bc_{kitchen}/seed0 where it exists); a stand-in elsewhere")
    simulating.add_argument("--stand-in", metavar="CONVENTION",
                            help="the zoo convention every stand-in plays (default: each participant draws one of the "
                                 "zoo's training conventions); scripted_cook: the default convention")
    simulating.add_argument("--parallel", type=int, default=4, help="participants visiting at once")
    simulating.add_argument("--keep-pace", action="store_true",
                            help="the config's own pace (default: turns, a step as soon as a key arrives)")
    simulating.add_argument("--max-steps", type=int, metavar="STEPS",
                            help="games (and practice games) of at most STEPS steps: a quick try of the machinery")
    simulating.set_defaults(handle=simulate)
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return args.handle(args)
    except StudyError as failure:
        return error(str(failure))


if __name__ == "__main__":
    sys.exit(main())
