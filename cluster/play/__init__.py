"""Browser play: the game loop, the message protocol, sessions and the HTTP server (static page in ``static/``)."""
