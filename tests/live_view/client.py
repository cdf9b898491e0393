"""A minimal Foxglove WebSocket client (subprotocol foxglove.sdk.v1, which the foxglove 0.30 server speaks): subscribe to one topic and
print every message data frame received on it as a JSON line {log_time_ns, payload_hex}
(after a line {"connected": true} once the server accepted the connection; the server's
status messages, e.g. a refused subscription, as lines {"status": ...}).

Usage: client.py ws://HOST:PORT TOPIC COUNT
"""
import asyncio
import json
import struct
import sys

import websockets


async def main(url, topic, count):
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        print(json.dumps({"connected": True}), flush=True)
        subscribed = None
        received = 0
        while received < count:
            frame = await asyncio.wait_for(ws.recv(), timeout=120)
            if isinstance(frame, str):
                message = json.loads(frame)
                if message.get("op") == "advertise" and subscribed is None:
                    for channel in message["channels"]:
                        if channel["topic"] == topic:
                            print(json.dumps({"advertised": channel}), flush=True)
                            await ws.send(json.dumps({
                                "op": "subscribe",
                                "subscriptions": [{"id": 7, "channelId": channel["id"]}],
                            }))
                            subscribed = 7
                elif message.get("op") == "status":
                    print(json.dumps({"status": message}), flush=True)
                continue
            # Binary: opcode 1 = message data: u32 subscription id, u64 log time, payload.
            if frame[0] != 1:
                continue
            sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
            if sub_id != subscribed:
                continue
            print(json.dumps({"log_time_ns": log_time, "payload_hex": frame[13:].hex()}), flush=True)
            received += 1


asyncio.run(main(sys.argv[1], sys.argv[2], int(sys.argv[3])))
