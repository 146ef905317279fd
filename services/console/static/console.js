// The console's own script (no inline scripts: the pages' Content-Security-Policy forbids them).
// Forms marked data-confirm ask before they post: deleting a run cannot be undone.
document.addEventListener("submit", (event) => {
  const form = event.target;
  const question = form.getAttribute && form.getAttribute("data-confirm");
  if (question && !window.confirm(question)) {
    event.preventDefault();
  }
}, true);
