"""The web apps where people play with trained teams: `play` (kitchen-play, a game in the browser) and `study`
(kitchen-study, a human study end to end)."""
