// The Rerun web viewer on the run's viewer page. The depot serves the viewer of its Rerun version
// (the rerun-notebook package's widget.js, which loads re_viewer_bg.wasm beside it); widget.js is an
// anywidget module, so it is given a small stand-in for the notebook's model: the recording's
// signed link (from the page's data-url) and the viewer's size.
const element = document.getElementById("viewer");
const status = document.getElementById("viewer-status");

function say(text) {
  if (status) {
    status.textContent = text;
  }
}

// Viewer events that say the run is on screen: it opened the recording, or its time cursor moved
// on the run's timelines (the first data shown). Anything else leaves the status as it was.
const SHOWN = new Set(["recording_open", "timeline_change", "time_update"]);

function runShown(message) {
  let event = message;
  if (typeof message === "string") {
    try {
      event = JSON.parse(message);
    } catch {
      return false;
    }
  }
  return Boolean(event && SHOWN.has(event.type));
}

function model(values) {
  const handlers = {};
  return {
    get: (name) => values[name],
    set: (name, value) => {
      values[name] = value;
    },
    on: (event, handler) => {
      (handlers[event] = handlers[event] || []).push(handler);
    },
    off: (event) => {
      delete handlers[event];
    },
    // What the viewer tells the notebook ("ready", then its events as JSON): shown as the page's status.
    send: (message) => {
      if (message === "ready") {
        if (element.dataset.state !== "loaded") {
          say("Viewer ready: loading the run…");
          element.dataset.state = "ready";
        }
        return;
      }
      if (runShown(message)) {
        say("Run loaded.");
        element.dataset.state = "loaded";
      }
    },
    save_changes: () => {},
  };
}

async function start() {
  if (!element) {
    return;
  }
  try {
    const widget = await import(element.dataset.widget);
    const values = {
      _url: new URL(element.dataset.url, document.baseURI).href, // a path on this page's origin
      _width: "auto",
      _height: Math.max(480, element.clientHeight),
      _panel_states: null,
      _fallback_token: null,
      _theme: null,
    };
    widget.default.render({ model: model(values), el: element });
    element.dataset.state = "started";
    say("Starting the viewer…");
  } catch (error) {
    element.dataset.state = "failed";
    say(`The web viewer failed to start: ${error}`);
  }
}

start();
