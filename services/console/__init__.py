"""The web console (`/console/`): pages rendered on the server from the same service functions the
REST API answers with, a small script (htmx) served by the depot, login by token into a session
cookie, CSRF checks on every action. See docs/console.md."""
