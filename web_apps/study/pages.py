"""The pages of a participant's visit, one per stage, and the operator's progress page: plain HTML written here,
the game drawn by kitchen-play's own script (web_apps/play/static/kitchen.js).

Each page speaks the study's protocol (`web_apps.study.server`): a stage is done by `POST
/api/p/<key>/stages/<stage>` (consent, instructions, questions) or by playing its game through over the WebSocket
`/ws/p/<key>/stages/<stage>`; the page then reloads, and the server draws the participant's next stage.
"""

from __future__ import annotations

import html
import json

from web_apps.study.assignment import COMPLETE, CONSENT, GAME, INSTRUCTIONS, PRACTICE, QUESTIONS, Stage
from web_apps.study.config import FORCED_CHOICE, StudyConfig

STYLE = """
  body { font-family: sans-serif; margin: 24px auto; max-width: 720px; background: #f4f1ea; color: #222; }
  h1 { font-size: 22px; } p { line-height: 1.45; }
  button { margin-top: 14px; padding: 6px 18px; font-size: 15px; }
  .error { color: #b00020; margin-top: 10px; min-height: 1em; }
  fieldset { border: 1px solid #bbb; margin: 12px 0; } legend { font-weight: bold; }
  label { margin-right: 14px; white-space: nowrap; } canvas { border: 2px solid #444; background: #ddd; }
  #status span { margin-right: 18px; } table { border-collapse: collapse; } td, th { padding: 3px 10px; }
"""
# Posts the stage's answers and reloads on success; shows the server's one-line refusal otherwise, or that it did
# not answer (restarting, or the connection lost): the participant may post again, stored once.
POST_SCRIPT = """
async function done(body) {
  const error = document.getElementById("error");
  try {
    const response = await fetch(`/api/p/${KEY}/stages/${STAGE}?token=${encodeURIComponent(TOKEN)}`,
      {method: "POST", headers: {"Content-Type": "application/json"}, body: JSON.stringify(body)});
    if (response.ok) { location.reload(); return; }
    const reply = await response.json().catch(() => ({}));
    error.textContent = typeof reply.detail === "string" ? reply.detail
      : `The study refused this page (${response.status}): reload it.`;
  } catch (failure) {
    error.textContent = "The study's server did not answer: wait a moment and try again.";
  }
}
"""
GAME_SCRIPT = """
const socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}` +
                             `/ws/p/${KEY}/stages/${STAGE}?token=${encodeURIComponent(TOKEN)}`);
const error = document.getElementById("error");
socket.onmessage = (event) => {
  const message = JSON.parse(event.data);
  if (message.type === "state") draw(message);
  if (message.type === "error") error.textContent = message.reason;
};
socket.onclose = () => {
  if (!document.getElementById("over").textContent) {
    error.textContent = error.textContent || "The connection to the game was lost: reload the page to play it again.";
    document.getElementById("again").textContent = "Reload";
  }
  document.getElementById("again").style.display = "inline";
};
document.addEventListener("keydown", (event) => {
  const action = KEYS[event.key];
  if (action && socket.readyState === WebSocket.OPEN) {
    socket.send(JSON.stringify({type: "action", action: action}));
    event.preventDefault();
  }
});
document.getElementById("again").onclick = () => location.reload();
"""


def paragraphs(text: str) -> str:
    return "".join(f"<p>{html.escape(part.strip())}</p>" for part in text.split("\n\n") if part.strip())


def script_values(**values) -> str:
    """JavaScript constants of `values`, safe inside a <script> element."""
    safe = {name: json.dumps(value).replace("</", "<\\/") for name, value in values.items()}
    return "".join(f"const {name} = {value};\n" for name, value in safe.items())


def document(title: str, body: str, script: str = "") -> str:
    return (f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{STYLE}</style></head><body>\n<h1>{html.escape(title)}</h1>\n{body}\n"
            + (f"<script>\n{script}</script>\n" if script else "") + "</body></html>\n")


def without_id_page(config: StudyConfig) -> str:
    """The page of a visit whose link does not name the participant (`participant_param`): nothing is registered."""
    return document(config.name, paragraphs(
        "This study is opened through the link of the platform you were recruited on, which says who you are. "
        "Please go back to the study's page there and open it from its link.\n\n"
        f"(The link lacks its {config.participant_param} parameter.)"))


def stage_page(config: StudyConfig, stage: Stage, stages: list[Stage], key: str, token: str, code: str) -> str:
    """The page of the participant's current `stage`."""
    constants = script_values(KEY=key, STAGE=stage.index, TOKEN=token)
    games = sum(s.kind == GAME for s in stages)
    error = '<div id="error" class="error"></div>'
    if stage.kind == CONSENT:
        return document("Consent", paragraphs(config.text("consent")) + '<button id="agree" onclick="done('
                        '{consent: true})">I agree to take part</button>' + error, constants + POST_SCRIPT)
    if stage.kind == INSTRUCTIONS:
        return document("How to play", paragraphs(config.text("instructions")) + '<button id="start" '
                        'onclick="done({})">Start</button>' + error, constants + POST_SCRIPT)
    if stage.kind in (PRACTICE, GAME):
        from web_apps.play.server import drawing_script

        practice = stage.kind == PRACTICE
        title = f"Practice game {stage.slot.position + 1}" if practice else f"Game {stage.slot.position + 1} of {games}"
        body = (paragraphs(config.text("practice")) if practice else "") + (
            '<div id="status"><span id="score"></span><span id="time"></span><span id="holding"></span></div>'
            '<canvas id="canvas" width="448" height="448"></canvas><div id="over"></div>' + error
            + '<button id="again" style="display:none">Continue</button>')
        return document(title, body, constants + drawing_script() + GAME_SCRIPT)
    if stage.kind == QUESTIONS:
        return document(f"After game {stage.slot.position + 1}", questions_form(config, stage) + error,
                        constants + POST_SCRIPT + answers_script(config, stage))
    assert stage.kind == COMPLETE
    link = config.completion_url.replace("{code}", code)
    return document("Thank you", paragraphs(config.text("complete"))
                    + f'<p>Your completion code: <strong id="code">{html.escape(code)}</strong></p>'
                    + (f'<p><a id="return" href="{html.escape(link)}">Return to the study\'s site</a></p>'
                       if link else ""))


def asks_forced_choice(config: StudyConfig, stage: Stage) -> bool:
    """Whether the questions after this game ask which of the last two partners to play with again."""
    return bool(config.forced_choice) and len(config.conditions) > 1 and stage.slot.position > 0


def allowed_answers(config: StudyConfig, stage) -> dict[str, list[int]]:
    """What a questions stage asks, with each answer's allowed values: every Likert item 1..len(scale), and the
    forced choice (where asked) the position of one of the last two games."""
    allowed = {item: list(range(1, len(config.likert.scale) + 1)) for item in config.likert.items}
    if asks_forced_choice(config, stage):
        allowed[FORCED_CHOICE] = [stage.slot.position - 1, stage.slot.position]
    return allowed


def questions_form(config: StudyConfig, stage: Stage) -> str:
    scale = config.likert.scale
    parts = [paragraphs(config.text("questions"))]
    for item, statement in config.likert.items.items():
        options = "".join(f'<label><input type="radio" name="{item}" value="{value}"> {html.escape(label)}</label>'
                          for value, label in enumerate(scale, 1))
        parts.append(f"<fieldset><legend>{html.escape(statement)}</legend>{options}</fieldset>")
    if asks_forced_choice(config, stage):
        position = stage.slot.position
        options = "".join(f'<label><input type="radio" name="{FORCED_CHOICE}" value="{value}"> {label}</label>'
                          for value, label in ((position - 1, f"the partner of game {position}"),
                                               (position, f"the partner of game {position + 1} (this one)")))
        parts.append(f"<fieldset><legend>{html.escape(config.forced_choice)}</legend>{options}</fieldset>")
    parts.append('<button id="send" onclick="send()">Continue</button>')
    return "".join(parts)


def answers_script(config: StudyConfig, stage: Stage) -> str:
    return script_values(ITEMS_ASKED=list(allowed_answers(config, stage))) + """
function send() {
  const answers = {};
  for (const item of ITEMS_ASKED) {
    const chosen = document.querySelector(`input[name="${item}"]:checked`);
    if (!chosen) { document.getElementById("error").textContent = "Please answer every question."; return; }
    answers[item] = Number(chosen.value);
  }
  done({answers: answers});
}
"""


OPERATOR_REFRESH_S = 10  # the operator's page reloads itself


def progress_page(name: str, progress: dict, target: int) -> str:
    """The operator's page: participants started and finished, games per condition and kitchen."""
    def table(title: str, counts: dict) -> str:
        rows = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{v}</td></tr>" for k, v in counts.items())
        return f"<h2>{title}</h2><table><tr><th></th><th>games finished</th></tr>{rows}</table>"

    summary = {"participants started": progress["started"], "consented": progress["consented"],
               "finished": progress["finished"] if not target else f"{progress['finished']} of {target}",
               "games finished (not practice)": progress["games_finished"],
               "practice games finished": progress["practice_finished"],
               "games cut and played again": progress["games_cut"], "games playing now": progress["playing"],
               "answers stored": progress["answers"]}
    rows = "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in summary.items())
    design = "".join(f"<tr><td>{row}</td>" + "".join(f"<td>{n}</td>" for n in states.values()) + "</tr>"
                     for row, states in progress["rows"].items())
    return document(f"Study {name}: progress", f"<p>This page refreshes itself every {OPERATOR_REFRESH_S} s.</p>"
                    f"<table>{rows}</table>" + table("Per condition", progress["per_condition"])
                    + table("Per kitchen", progress["per_kitchen"])
                    + "<h2>The design's rows</h2><table><tr><th>row</th><th>finished</th><th>in progress</th>"
                    f"<th>abandoned</th></tr>{design}</table>",
                    script=f"setTimeout(() => location.reload(), {OPERATOR_REFRESH_S * 1000});\n")
