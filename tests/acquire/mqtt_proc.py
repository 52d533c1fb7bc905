"""An MQTT status publisher in its own process, for the last-will test (not a test module).

    python mqtt_proc.py PORT VESSEL

Publishes ``status`` {"state": "running"} and prints ``READY`` once the broker has it.
"""

from __future__ import annotations

import asyncio
import sys

from acquire.status.bus import StatusBus
from acquire.status.mqtt import MqttPublisher, MqttSettings


async def main() -> None:
    port, vessel = int(sys.argv[1]), sys.argv[2]
    pub = MqttPublisher(MqttSettings("127.0.0.1", port, keepalive_s=5), vessel)
    bus = StatusBus([pub])
    task = asyncio.create_task(pub.run())
    bus.publish("status", {"state": "running"})
    while pub.published < 1:
        await asyncio.sleep(0.01)
    print("READY", flush=True)
    await task


if __name__ == "__main__":
    asyncio.run(main())
