"""Partners that are not the team being trained: the scripted cook (`scripted_cook`) and its conventions with the zoo
file (`conventions`), zoo cooks seated in a learner's kitchens (`zoo_seats`), and two teams seated in one kitchen
(`pairing`)."""
