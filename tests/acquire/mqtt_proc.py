"""An MQTT status publisher in its own process, for the last-will test (not a test module).

    python mqtt_proc.py PORT VESSEL

Publishes ``status`` {"state": "running"} and prints ``READY`` once the broker has it.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

from acquire.status.bus import StatusBus
from acquire.status.mqtt import MqttPublisher, MqttSettings

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run as a script: the tests package
from tests.waiting import wait_until_async  # noqa: E402


async def main() -> None:
    port, vessel = int(sys.argv[1]), sys.argv[2]
    pub = MqttPublisher(MqttSettings("127.0.0.1", port, keepalive_s=5), vessel)
    bus = StatusBus([pub])
    task = asyncio.create_task(pub.run())
    bus.publish("status", {"state": "running"})
    await wait_until_async(lambda: pub.published >= 1, 30, "the broker to have the status")
    print("READY", flush=True)
    await task


if __name__ == "__main__":
    asyncio.run(main())
