// The console's small DOM helpers: text-only nodes (client-chosen names never become markup) and
// a card's status line, shared by the project page's modules.

export const $ = (id) => document.getElementById(id);

export function text(tag, className, value) {
  const node = document.createElement(tag);
  if (className) node.className = className;
  node.textContent = value;
  return node;
}

export function setStatus(id, state, message) {
  const s = $(id);
  s.dataset.state = state;
  s.textContent = message;
}
