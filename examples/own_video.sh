#!/usr/bin/env bash
# Your own phone video, step by step. Replace the paths; each command has --help.
set -euo pipefail
VIDEO=${1:-room.mp4}
DS=${2:-out/room}

# 1. frames: the sharpest frame per window, named by their index in the video
interreal frames "$VIDEO" "$DS" --target 200 --long-side 960

# 2. annotate: draw each object's mask on a few frames and set its state (0 closed .. 1 open) on a few frames;
#    the page runs mask propagation for you and suggests which frame to annotate next
interreal annotate "$DS"            # prints a URL with a one-time token; open it in your browser

# (or, with annotations made elsewhere: interreal masks "$DS" --keyframes my_keyframes/
#                                        interreal label "$DS" --from my_states.csv)

# 3. poses: pycolmap SfM with the object pixels masked out
interreal poses "$DS"

# 4. motions: each part's hinge or slide measured from its own pixels, so it moves from every view; the labels
#    only say which end is closed, and a label the geometry disagrees with is named (fix it in the app, one click)
interreal motions "$DS"
interreal label "$DS" --describe "fridge door" "the thing that keeps food cold"   # text finds it by what it does
interreal validate "$DS"

# 5. train, then render the fridge half open, and a sweep of the drawer
livescene train "$DS" --out "$DS.run"
livescene render "$DS.run" --state "fridge door=0.5" --out "$DS.renders"
livescene render "$DS.run" --sweep "top drawer=0:1:30" --video "$DS.renders/drawer.mp4"
livescene ground "$DS.run" "the thing that keeps food cold" --out "$DS.ground"
