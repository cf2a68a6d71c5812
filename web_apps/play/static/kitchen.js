// Drawing a kitchen's state as the server sends it (web_apps.play.game.Game.view), and the keys a player
// presses; shared by kitchen-play's lobby and kitchen-study's game stages, inlined into their pages.
// The page holds elements #canvas, #score, #time, #holding, #over and #again.
// Cell kinds and item codes of jax_env: FLOOR, COUNTER, ONION_PILE, PLATE_PILE, POT, GOAL; items 0 none, 1 onion, 2 plate, 3 soup.
const KIND_COLOURS = ["#e9e2d0", "#a67c52", "#c9b26b", "#d8d8d8", "#555555", "#7fb069"];
const ITEMS = ["nothing", "an onion", "a plate", "a soup"];
const SEAT_COLOURS = ["#d63031", "#2662d6"];  // jax_env.render.AGENT_COLOURS: the GIFs' colours
const KEYS = {ArrowUp: "up", ArrowDown: "down", ArrowLeft: "left", ArrowRight: "right", " ": "interact",
              w: "up", s: "down", a: "left", d: "right", e: "interact", W: "up", S: "down", A: "left", D: "right", E: "interact"};
const DIRS = [[0, -1], [0, 1], [1, 0], [-1, 0]];

function drawItem(ctx, item, x, y, r) {
  if (item === 1) { ctx.fillStyle = "#f2e85c"; ctx.beginPath(); ctx.arc(x, y, r, 0, 7); ctx.fill(); }
  if (item >= 2) { ctx.fillStyle = "#ffffff"; ctx.beginPath(); ctx.arc(x, y, r * 1.3, 0, 7); ctx.fill(); }
  if (item === 3) { ctx.fillStyle = "#e07a3f"; ctx.beginPath(); ctx.arc(x, y, r * 0.8, 0, 7); ctx.fill(); }
}

function draw(state) {
  const canvas = document.getElementById("canvas");
  const size = Math.floor(448 / Math.max(state.width, state.height));
  canvas.width = size * state.width; canvas.height = size * state.height;
  const ctx = canvas.getContext("2d");
  for (let y = 0; y < state.height; y++) for (let x = 0; x < state.width; x++) {
    const kind = state.kinds[y][x], value = state.contents[y][x];
    ctx.fillStyle = KIND_COLOURS[kind]; ctx.fillRect(x * size, y * size, size, size);
    ctx.strokeStyle = "#00000022"; ctx.strokeRect(x * size, y * size, size, size);
    const cx = x * size + size / 2, cy = y * size + size / 2;
    if (kind === 1) drawItem(ctx, value, cx, cy, size / 6);
    if (kind === 2) drawItem(ctx, 1, cx, cy, size / 5);
    if (kind === 3) drawItem(ctx, 2, cx, cy, size / 6);
    if (kind === 4) {  // pot: 23 empty, 20-22 filling, 1-19 cooking, 0 ready
      ctx.fillStyle = "#222"; ctx.beginPath(); ctx.arc(cx, cy, size / 3, 0, 7); ctx.fill();
      ctx.fillStyle = "#fff"; ctx.font = `${Math.floor(size / 4)}px sans-serif`; ctx.textAlign = "center";
      const label = value === 0 ? "ready" : value < 20 ? String(value) : value < 23 ? "o".repeat(23 - value) : "";
      ctx.fillText(label, cx, cy + size / 10);
    }
    if (kind === 5) { ctx.fillStyle = "#fff"; ctx.font = `${Math.floor(size / 4)}px sans-serif`; ctx.textAlign = "center"; ctx.fillText("serve", cx, cy + size / 10); }
  }
  state.positions.forEach(([x, y], agent) => {
    const cx = x * size + size / 2, cy = y * size + size / 2;
    ctx.fillStyle = SEAT_COLOURS[agent]; ctx.beginPath(); ctx.arc(cx, cy, size / 2.8, 0, 7); ctx.fill();
    if (agent === state.seat) { ctx.lineWidth = 3; ctx.strokeStyle = "#000"; ctx.stroke(); ctx.lineWidth = 1; }
    const [dx, dy] = DIRS[state.directions[agent]];
    ctx.strokeStyle = "#000"; ctx.lineWidth = 3; ctx.beginPath(); ctx.moveTo(cx, cy);
    ctx.lineTo(cx + dx * size / 2.2, cy + dy * size / 2.2); ctx.stroke(); ctx.lineWidth = 1;
    drawItem(ctx, state.holding[agent], cx, cy, size / 8);
  });
  document.getElementById("score").textContent = `score ${state.score}`;
  document.getElementById("time").textContent = `time left ${state.time_left}`;
  document.getElementById("holding").textContent =
    `you hold ${ITEMS[state.holding[state.seat]]}, your partner ${ITEMS[state.holding[1 - state.seat]]}`;
  if (state.over) {
    document.getElementById("over").textContent = `Game over: ${state.score} ${state.score === 1 ? "soup" : "soups"} delivered.`;
    document.getElementById("again").style.display = "inline";
  }
}
