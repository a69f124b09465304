#!/usr/bin/env bash
# Your own phone video, step by step. Replace the paths; each command has --help.
#   bash examples/own_video.sh room.mp4 out/room                     # draws the masks in your browser (step 2)
#   KEYFRAMES=kf/ LABELS=states.csv bash examples/own_video.sh room.mp4 out/room   # annotations made elsewhere
# TRAIN_ARGS adds flags to `livescene train` (e.g. "--max-minutes 15"); OBJECT names the part to sweep (default: the
# dataset's first object). tests/test_examples.py runs this script on a small simulated capture.
set -euo pipefail
VIDEO=${1:-room.mp4}
DS=${2:-out/room}

# 1. frames: the sharpest frame per window, named by their index in the video
interreal frames "$VIDEO" "$DS" --target 200 --long-side 960

# 2. masks and states: draw each object's mask on a few frames and set its state (0 closed .. 1 open) on a few;
#    the page runs mask propagation for you and suggests which frame to annotate next. Hands and arms are found
#    without painting (--transients auto).
if [ -n "${KEYFRAMES:-}" ]; then
  interreal masks "$DS" --keyframes "$KEYFRAMES"
  if [ -n "${LABELS:-}" ]; then interreal label "$DS" --from "$LABELS"; fi
else
  interreal annotate "$DS"          # prints a URL with a one-time token; open it in your browser; Ctrl-C when done
fi

# 3. poses: pycolmap SfM with the object pixels (and hands) masked out
interreal poses "$DS"

# 4. motions: each part's hinge or slide measured from its own pixels, so it moves from every view; the labels
#    only say which end is closed, and a label the geometry disagrees with is named (fix it in the app, one click)
interreal motions "$DS"
OBJECT=${OBJECT:-$(interreal label "$DS" --objects | head -n 1)}
interreal label "$DS" --describe "$OBJECT" "the part that opens"   # text grounding finds it by what it does
interreal validate "$DS"

# 5. train, render the part half open and a sweep of it, find it by text, export it for a simulator
# shellcheck disable=SC2086  # TRAIN_ARGS is a list of flags
livescene train "$DS" --out "$DS.run" ${TRAIN_ARGS:-}
livescene render "$DS.run" --state "$OBJECT=0.5" --out "$DS.renders"
livescene render "$DS.run" --sweep "$OBJECT=0:1:5" --video "$DS.renders/sweep.mp4"
livescene ground "$DS.run" "the part that opens" --out "$DS.ground"
livescene export "$DS.run" --format urdf --out "$DS.asset"
echo "done: open the renders in $DS.renders, or run: livescene view $DS.run"
