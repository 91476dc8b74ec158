"""``overgrid view``: the live map in a browser (aiohttp server, canvas page, WebSocket pushes)."""
