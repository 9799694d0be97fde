"""Scripted controllers, written in jnp so they run inside a `lax.scan` (and under `vmap`).

They serve two users: the physics tests (tests/test_fetch.py, test_tabletop.py, test_sawyer_door.py) and
the demonstrations MEDAL needs (morefree_jax.baselines.medal.demo_rollouts). The task controllers share one
signature, `controller(obs, goal, phase) -> (action, phase)`: `goal` is a full goal observation (as
`env.eval_goals` returns it), `phase` an int32 scalar that starts at 0 and carries what the controller
has done so far (grasped, passed a corner, ...). `CONTROLLERS` maps (task, direction) to one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from envs_mjx import fetch, point_umaze, tabletop
from envs_mjx import sawyer_door as door

# ---- Fetch ------------------------------------------------------------------------------------------
HOVER_Z = 0.48  # finger bottoms 1.5 cm above the block top
PUSH_Z = 0.43


def push_action(obs: jax.Array, goal: jax.Array) -> jax.Array:
    """Fingers closed: go up, come down behind the block, push it along the line to the goal (3,)."""
    grip, block = obs[0:3], obs[3:6]
    to_goal = goal[:2] - block[:2]
    distance = jnp.linalg.norm(to_goal)
    along_dir = to_goal / jnp.maximum(distance, 1e-6)
    side_dir = jnp.array([-along_dir[1], along_dir[0]])
    offset = grip[:2] - block[:2]
    along, side = offset @ along_dir, offset @ side_dir
    behind = block[:2] - 0.065 * along_dir
    at_behind = jnp.linalg.norm(grip[:2] - behind) < 0.012
    pushing = (jnp.abs(side) < 0.012) & (along < -0.02) & (grip[2] < PUSH_Z + 0.015)
    # Slow down near the goal: a block pushed at full speed (1.25 m/s) slides ~8 cm on after contact.
    push_xy = grip[:2] + jnp.minimum(0.5 * distance, 0.03) * along_dir - side * side_dir
    high_enough = grip[2] > HOVER_Z - 0.015
    approach_xy = jnp.where(high_enough | at_behind, behind, grip[:2])
    approach_z = jnp.where(at_behind, PUSH_Z, HOVER_Z)
    target = jnp.where(pushing, jnp.append(push_xy, PUSH_Z), jnp.append(approach_xy, approach_z))
    target = jnp.where(distance < 0.01, grip, target)
    return jnp.append(jnp.clip((target - grip) / fetch.MAX_DISPLACEMENT, -1, 1), -1.0)


def pick_action(obs: jax.Array, goal: jax.Array, phase: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Phases: 0 open above the block and descend, 1..3 close, 4 carry the block to the goal (3,)."""
    grip, block = obs[0:3], obs[3:6]
    above = jnp.linalg.norm(grip[:2] - block[:2]) < 0.01
    approach = jnp.where(above, block, jnp.append(block[:2], HOVER_Z))
    reach_action = jnp.append(jnp.clip((approach - grip) / fetch.MAX_DISPLACEMENT, -1, 1), 1.0)
    close_action = jnp.array([0.0, 0.0, 0.0, -1.0])
    carry_action = jnp.append(jnp.clip((goal - block) / fetch.MAX_DISPLACEMENT, -1, 1), -1.0)
    action = jnp.where(phase == 0, reach_action, jnp.where(phase < 4, close_action, carry_action))
    reached = jnp.linalg.norm(grip - block) < 0.008
    dropped = jnp.linalg.norm(grip - block) > 0.03
    next_phase = jnp.where(phase == 0, reached.astype(jnp.int32), jnp.minimum(phase + 1, 4))
    next_phase = jnp.where((phase == 4) & dropped, 0, next_phase)
    return action, next_phase


def fetch_push(obs, goal, phase):
    return push_action(obs, goal[3:6]), phase


def fetch_pick(obs, goal, phase):
    return pick_action(obs, goal[3:6], phase)


# ---- Tabletop ---------------------------------------------------------------------------------------
OPEN, CLOSE = -1.0, 1.0


def tabletop_waypoint_action(obs: jax.Array, waypoint: jax.Array) -> jax.Array:
    """Moves the gripper straight to waypoint[0:2] (exactly, 0.2 per axis and step), grasp waypoint[2]."""
    move = jnp.clip((waypoint[0:2] - obs[0:2]) / tabletop.MOVE_SCALE, -1.0, 1.0)
    return jnp.concatenate([move, waypoint[2:3]])


def tabletop_carry(obs, goal, phase):
    """Carries the mug to goal[2:4] and parks the gripper at goal[0:2], from wherever both are. Phases:
    0 go to the mug, 1 grasp, 2 carry, 3 release, 4 park. A phase ends once the gripper is at its point
    with the grasp state it asks for, so the same controller serves forward and reverse episodes."""
    mug, goal_mug, goal_gripper = obs[2:4], goal[2:4], goal[0:2]
    points = jnp.stack([mug, mug, goal_mug, goal_mug, goal_gripper])
    grasps = jnp.array([OPEN, CLOSE, CLOSE, OPEN, OPEN])
    held = obs[4] > 0.5 * (tabletop.FREE + tabletop.HELD)
    at_point = jnp.linalg.norm(obs[0:2] - points[phase]) < 1e-3
    done = at_point & (held == (grasps[phase] > 0))
    phase = jnp.minimum(phase + done.astype(jnp.int32), 4)
    waypoint = jnp.append(points[phase], grasps[phase])
    return tabletop_waypoint_action(obs, waypoint), phase


# ---- Sawyer Door ------------------------------------------------------------------------------------
PUSH_RADIUS, PUSH_Z_DOOR = 0.30, 0.18  # push the leaf 0.30 from the hinge, above the handle (top z 0.123)
# Pull open: the hand sits between the handle bar and the leaf (leaf frame x 0.338..0.433, y -0.01..-0.097)
# and pulls the bar towards the robot; its pads (half depth 0.015) touch the bar when the hand is 0.082
# in front of the leaf.
PULL_RADIUS, PULL_FRONT, PULL_Z, ABOVE_HANDLE_Z = 0.385, 0.082, 0.10, 0.20
FINGERS_CLOSED = 1.0


def leaf_point(angle, radius, front, z):
    """World point `radius` along the leaf at door angle `angle`, `front` in front of it (handle side)."""
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    x, y = radius, -front
    return jnp.stack([door.HINGE[0] + cos * x - sin * y, door.HINGE[1] + sin * x + cos * y, jnp.asarray(z)])


def steer(obs, target):
    """Hand motion (3,) towards `target` at up to 1 cm per axis and step."""
    return jnp.clip((target - obs[0:3]) / door.MOCAP_STEP, -1.0, 1.0)


def with_fingers_closed(move):
    return jnp.append(move, FINGERS_CLOSED)


def close_door(obs, goal, phase):
    """Go in front of the leaf, then push it shut along its arc; fingers closed."""
    del goal  # the only goal is the closed door
    angle = door.door_angle_of_handle(obs[4:7])
    approach = leaf_point(angle, PUSH_RADIUS, 0.045, PUSH_Z_DOOR)
    push = leaf_point(jnp.minimum(angle + 0.2, 0.0), PUSH_RADIUS, 0.025, PUSH_Z_DOOR)
    phase = jnp.maximum(phase, (jnp.linalg.norm(obs[0:3] - approach) < 0.015).astype(jnp.int32))
    return with_fingers_closed(steer(obs, jnp.where(phase > 0, push, approach))), phase


def push_door_open(obs, goal, phase):
    """Rise, pass over the leaf, drop behind it and keep pushing it further open into the stopper."""
    del goal
    angle = door.door_angle_of_handle(obs[4:7])
    behind = leaf_point(angle, PUSH_RADIUS, -0.045, PUSH_Z_DOOR)
    targets = jnp.stack(
        [
            obs[0:3].at[2].set(0.32),
            behind.at[2].set(0.32),
            behind,
            leaf_point(angle - 0.3, PUSH_RADIUS, -0.025, PUSH_Z_DOOR),
        ]
    )
    reached = jnp.linalg.norm(obs[0:3] - targets[phase]) < 0.015
    phase = jnp.minimum(phase + reached.astype(jnp.int32), 3)
    return with_fingers_closed(steer(obs, targets[phase])), phase


def pull_door_open(obs, goal, phase):
    """Open the door to the goal's angle by the handle: rise, go above the gap between the handle bar and
    the leaf, drop into it, then pull the bar along the arc, at most 0.2 rad ahead of the door, until the
    door stands at the angle of goal[4:7] (the workspace ends in front of the closed door, so a hand
    cannot get behind the leaf to push it open)."""
    angle = door.door_angle_of_handle(obs[4:7])
    goal_angle = door.door_angle_of_handle(goal[4:7])
    in_gap = leaf_point(angle, PULL_RADIUS, 0.05, PULL_Z)
    pull_angle = angle + jnp.clip(goal_angle - angle, -0.2, 0.2)
    targets = jnp.stack(
        [
            obs[0:3].at[2].set(ABOVE_HANDLE_Z),
            in_gap.at[2].set(ABOVE_HANDLE_Z),
            in_gap,
            leaf_point(pull_angle, PULL_RADIUS, PULL_FRONT, PULL_Z),
        ]
    )
    reached = jnp.linalg.norm(obs[0:3] - targets[phase]) < 0.015
    phase = jnp.minimum(phase + reached.astype(jnp.int32), 3)
    return with_fingers_closed(steer(obs, targets[phase])), phase


# ---- PointUMaze -------------------------------------------------------------------------------------
# The corridor's corners: the centres of the free cells at the far end of the U (row 1 and row 3, col 3).
UMAZE_CORNERS = np.array([point_umaze.cell_center(1, 3), point_umaze.cell_center(3, 3)], np.float32)
CORNER_RADIUS = 1.0  # head for the next waypoint once this close to a corner


def umaze_drive(obs, goal, phase):
    """Drive along the U's centre line: start cell -> both far corners -> goal. Turn towards the waypoint
    (at most 0.25 rad a step) and move forward by cos(heading error), so the point slows in turns and
    keeps to the corridor's middle, away from the walls (whose contacts would kick it)."""
    waypoints = jnp.concatenate([jnp.asarray(UMAZE_CORNERS), goal[None, 0:2]])
    near = jnp.linalg.norm(obs[0:2] - waypoints[phase]) < CORNER_RADIUS
    phase = jnp.minimum(phase + (near & (phase < 2)).astype(jnp.int32), 2)
    to_target = waypoints[phase] - obs[0:2]
    error = point_umaze.wrap_angle(jnp.arctan2(to_target[1], to_target[0]) - obs[2])
    turn = jnp.clip(error / point_umaze.MAX_TURN, -1.0, 1.0)
    forward = jnp.maximum(jnp.cos(error), 0.0) ** 3 * jnp.minimum(jnp.linalg.norm(to_target), 1.0)
    return jnp.stack([forward, turn]), phase


# (task, direction) -> controller(obs, goal, phase) -> (action, phase)
CONTROLLERS = {
    ("point_umaze", "forward"): umaze_drive,
    ("tabletop", "forward"): tabletop_carry,
    ("tabletop", "reverse"): tabletop_carry,
    ("sawyer_door", "forward"): close_door,
    ("sawyer_door", "reverse"): pull_door_open,
    ("push", "forward"): fetch_push,
    ("push_hard", "forward"): fetch_push,
    ("pick_place", "forward"): fetch_pick,
    ("pick_place_hard", "forward"): fetch_pick,
}
