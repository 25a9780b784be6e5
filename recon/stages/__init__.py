"""The pipeline's stages, in order. Each one plans (`recon.plans`), prints its reasons, calls the libraries and writes
its own folder.

The declarations below are all that fingerprints, `recon status` and the scene's folder names read: a stage's module
(and with it torch, trimesh, pycolmap) is imported when the stage runs, so looking at a scene loads none of them. A
stage's `version` goes up when its output changes for the same inputs and options: a scene made before runs it
again."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from recon.runner.pipeline import RECON_NAMES, Pipeline, Stage, StageContext


def _poses(ctx: StageContext) -> dict:
    from recon.stages.poses import run

    return run(ctx)


def _photos_digest(source: Path, cfg: Any) -> str:
    from recon.stages.poses import source_digest

    return source_digest(source, cfg)


def _photos_stat(source: Path) -> str:
    from recon.stages.poses import source_stat

    return source_stat(source)


def _normalize(ctx: StageContext) -> dict:
    from recon.stages.normalize import run

    return run(ctx)


def _train(ctx: StageContext) -> dict:
    from recon.stages.train import run

    return run(ctx)


def _mesh(ctx: StageContext) -> dict:
    from recon.stages.mesh import run

    return run(ctx)


# poses, version 6: turntable captures (features where the photos change, the still room kept for normalize); a final
# bundle adjustment that runs away is undone
# version 7: photos named by their place in the input folder ({source}/NAME); photos taken the other way up from most
#            turned a quarter for SfM to share one camera
# version 8: the pose outliers are judged after the final bundle adjustment too
POSES = Stage(name="poses", folder="01_poses", inputs=(), version=8, run=_poses, needs_source=True,
              source_digest=_photos_digest, source_stat=_photos_stat)

# normalize, version 6: automatic masks are soft at their outlines, snapped to the photos' edges
# version 7: a masked object's box holds the masks' visual hull
# version 8: automatic masks seeded by surely placed points only, each its own pixel
# version 9: automatic masks cut twice, the second time from the hull of the first cuts (undone in version 10)
# version 10: the object region holds the points linked to those most photos keep in frame
# version 11: no more photos held out than leave FEW_PHOTOS to train
# version 12: the object region holds what an object on a wall hangs on
# version 13: automatic masks start the cut with the object seeds' feet on the ground as probable object
# version 14: automatic masks drop what lines up with the table, give back bites whose rays meet it under the object,
#             and trust leaves lone points out
# version 15: automatic masks match the table only with photos that see the object move off its homography
# version 16: automatic masks are recorded relative to the scene folder (were relative to the working folder)
# version 17: automatic masks: only the photos that frame the object carve the hull; close-ups are cut again inside it
# version 18: automatic masks: a photo that frames the object but whose cut left out much of the hull is cut again
# version 19: automatic masks: the hull's silhouette splatted at each vertex's depth; a close-up it fills without
#             background points takes it; a cut reaching the pinhole image's edge reaches the photo's border
# version 20: automatic masks: object points nearly every mask leaves out (up to a tenth) do not count against them
# version 21: training photos far blurrier than those sharing their view are left out (normalize.blurred)
# version 22: groups of in-frame points the photos frame off to the side are no part of the object (normalize.beside)
# version 23: cameras converging from a narrow arc on an object standing on a support make an object capture
# version 24: up is orthogonal to level photos' right vectors from arcs down to about 40°, not their mean up vector
# version 25: the automatic masks take only the points normalize took for the object's as its seeds, and those it
# left out as things beside the object as background (a picture's corner inside the box of a head on a wall)
# version 26: the automatic masks' box holds every point normalize took for the object (a thin part's top)
# version 27: a photo with an empty automatic mask that observes next to none of the object's points is left out
NORMALIZE = Stage(name="normalize", folder="02_scene", inputs=("poses",), version=27, run=_normalize)

# train, version 2: train.depth_prior=auto turns the prior on for the surface model, so a cached surface field is stale
# version 3: the surface model keys a plain backdrop (train.backdrop_key) and starts from the SfM points' hull
# version 4: train.sky=auto gives an unbounded capture with a clear sky a sky colour and trains its sky pixels empty
# version 5: train.depth_prior=auto turns the prior on for unbounded captures without masks
# version 6: the surface model starts from the photos' visual hull when they have silhouettes
# version 7: close-ups train at the other photos' pixel footprint (train.photo_footprint)
# version 8: train.appearance=auto measures the exposure of photos cut out by masks on the whole photo
# version 9: train.appearance=auto also matches photos further apart, where a slow exposure drift shows
# version 10: train.hull_start=auto starts the fast field in the masks' hull unless the object hangs on a wall
# version 11: a fast field started empty though its photos have silhouettes culls untouched space later
# version 12: a field that culls slowly raises its occupancy threshold over 200 steps, not 1,000
# version 13: train.smoothness=auto smooths the plain faces of a field that starts empty though it has silhouettes
# version 14: the hull that says which transparent pixels are disputed is splatted at each vertex's depth
# version 15: train.depth_prior=auto is on for a fast field that starts empty though its photos have silhouettes
# version 16: a field started in the visual hull starts empty where sightlines to the sparse points pass (hollows)
# version 17: train.depth_prior=auto is on for a field started in a hull that sightlines pass through 10% of or more
# version 18: train.depth_prior=auto is on for a fast field under 20 training photos with masks too
TRAINS_ON_UNDER = ("budget", "eval_every", "checkpoint_every", "final_eval_views", "depth_rays")
"""The options a checkpoint or a finished field trains on under (the rest make another field, from step 0): the time
budget, how often training is watched and kept, how many test views score it, and the sparse-depth rays a step
renders (a term's sample size, drawn afresh each step) -- so `balanced` after `fast` trains fast's field on."""
TRAIN = Stage(name="train", folder="03_field", inputs=("normalize",), version=18, run=_train,
              scratch_survives=TRAINS_ON_UNDER)

# mesh, version 4: zero-area faces marching cubes leaves stay (dropping one opened a three-edge hole in a closed zero
# set)
# version 5: a field trained without the automatic masks (unsure) is meshed cropped by them
MESH = Stage(name="mesh", folder="04_mesh", inputs=("normalize", "train"), version=5, run=_mesh)

STAGES: list[Stage] = [POSES, NORMALIZE, TRAIN, MESH]


def default_pipeline() -> Pipeline:
    return Pipeline(STAGES)


def scene_parts() -> frozenset[str]:
    """What recon makes at the top of a scene folder (stage folders, manifest, lock, logs, scratch): no other
    output of recon may be written inside them (`recon.runner.ownership`)."""
    return RECON_NAMES | {s.folder for s in STAGES}
