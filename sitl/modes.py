"""Rover's mode numbers (Rover/mode.h Mode::Number) and what each needs (Mode::requires_position,
is_autopilot_mode). There are no modes 2, 13 and 14."""

from __future__ import annotations

MODE_MANUAL = 0
MODE_ACRO = 1
MODE_STEERING = 3
MODE_HOLD = 4
MODE_LOITER = 5
MODE_FOLLOW = 6
MODE_SIMPLE = 7
MODE_DOCK = 8
MODE_CIRCLE = 9
MODE_AUTO = 10
MODE_RTL = 11
MODE_SMART_RTL = 12
MODE_GUIDED = 15
MODE_INITIALISING = 16

MODE_NAMES = {0: "MANUAL", 1: "ACRO", 3: "STEERING", 4: "HOLD", 5: "LOITER", 6: "FOLLOW", 7: "SIMPLE",
              8: "DOCK", 9: "CIRCLE", 10: "AUTO", 11: "RTL", 12: "SMART_RTL", 15: "GUIDED", 16: "INITIALISING"}

# Modes that can be entered (when armed) without a position estimate.
NO_POSITION_NEEDED = frozenset({MODE_MANUAL, MODE_ACRO, MODE_STEERING, MODE_HOLD, MODE_INITIALISING})
# Modes that navigate themselves (NAV_CONTROLLER_OUTPUT is sent in these).
AUTOPILOT_MODES = frozenset({MODE_AUTO, MODE_CIRCLE, MODE_GUIDED, MODE_LOITER, MODE_RTL, MODE_SMART_RTL,
                             MODE_FOLLOW, MODE_DOCK})

# FS_ACTION / FENCE_ACTION (Rover's FailsafeAction).
ACTION_NONE = 0
ACTION_RTL = 1
ACTION_HOLD = 2
ACTION_SMART_RTL = 3
ACTION_SMART_RTL_HOLD = 4
ACTION_TERMINATE = 5
ACTION_LOITER_HOLD = 6
