"""Human studies around kitchen-play's games: a study's config (`config`), who plays what in which order
(`assignment`), its state in SQLite (`database`), the participants' pages and the server (`pages`, `server`), the
analysis (`analysis`), the `kitchen-study` command (`command`) and simulated participants for tests and load
benchmarks (`client`). See docs/study.md."""
