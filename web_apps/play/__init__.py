"""`kitchen-play`: a person cooks with a trained team in the browser; games are recorded and replayable."""
