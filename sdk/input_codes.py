"""Linux input-event codes that a gamepad binding may name, as the kernel names them.

Shared by the binding's validation (sdk, which may not import the runtime) and the evdev
decoder (rigspace.runtime.live.decoders.evdev). Values from linux/input-event-codes.h; the
names follow the gamepad's standard mapping (Documentation/input/gamepad.rst).
"""

from __future__ import annotations

EV_SYN, EV_KEY, EV_ABS = 0, 1, 3
ABS_CODES = {"ABS_X": 0, "ABS_Y": 1, "ABS_Z": 2, "ABS_RX": 3, "ABS_RY": 4, "ABS_RZ": 5}
ABS_CODES |= {"ABS_GAS": 9, "ABS_BRAKE": 10, "ABS_HAT0X": 16, "ABS_HAT0Y": 17}
BTN_CODES = {"BTN_SOUTH": 0x130, "BTN_EAST": 0x131, "BTN_NORTH": 0x133, "BTN_WEST": 0x134}
BTN_CODES |= {"BTN_TL": 0x136, "BTN_TR": 0x137, "BTN_TL2": 0x138, "BTN_TR2": 0x139}
BTN_CODES |= {"BTN_SELECT": 0x13A, "BTN_START": 0x13B, "BTN_MODE": 0x13C}
BTN_CODES |= {"BTN_THUMBL": 0x13D, "BTN_THUMBR": 0x13E}
CONTROL_CODES = {**{k: (EV_ABS, v) for k, v in ABS_CODES.items()}}
CONTROL_CODES |= {k: (EV_KEY, v) for k, v in BTN_CODES.items()}
"""Control name -> (event type, code)."""
