"""Real-time neural material viewer in the browser (docs/viewer.md): `web_bundle` turns an asset into files a WebGL2
page loads (`static/index.html`, `static/viewer.js`), `serve` serves them with the standard library's http.server."""
