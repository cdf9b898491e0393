"""Try to open the live view as a given client would, and say what it got as one JSON line:
{"status": 101, "first_op": "serverInfo"} when admitted (the first message's op), else
{"status": <HTTP status>, "body": "..."} when the server refused the handshake.

Usage: handshake.py ws://HOST:PORT/[?token=...] [ORIGIN|-] [BEARER|-] [COOKIE|-]
"""
import asyncio
import json
import sys

import websockets


async def main(url, origin, bearer, cookie):
    headers = {}
    if bearer != "-":
        headers["Authorization"] = f"Bearer {bearer}"
    if cookie not in ("-", ""):
        headers["Cookie"] = cookie
    kwargs = {"subprotocols": ["foxglove.sdk.v1"], "additional_headers": headers}
    if origin != "-":
        kwargs["origin"] = origin
    try:
        async with websockets.connect(url, **kwargs) as ws:
            frame = await asyncio.wait_for(ws.recv(), timeout=60)
            op = json.loads(frame).get("op") if isinstance(frame, str) else "binary"
            print(json.dumps({"status": 101, "first_op": op}), flush=True)
    except websockets.exceptions.InvalidStatus as refused:
        response = refused.response
        print(json.dumps({"status": response.status_code,
                          "body": response.body.decode("utf-8", "replace")}), flush=True)


asyncio.run(main(sys.argv[1], sys.argv[2], sys.argv[3], (sys.argv[4:] or ["-"])[0]))
