"""Photos a model left out, placed from their 2-D matches alone: COLMAP's structure-less
resectioning (`IncrementalMapper.register_next_structure_less_image`), called for each photo
still outside the model.

Why: COLMAP registers a photo from its matches to the model's 3-D points. A photo whose
matches with its registered neighbours fall on features no third photo saw (a two-view tie:
1334 verified matches with its neighbour, 8 of them on 3-D points, on a 57-photo survey at
1200 px) never becomes a candidate for registration, and its pipeline's structure-less
fallback never sees it: COLMAP only tries photos that see LEFT_OUT's 10 3-D points at least.
Structure-less resectioning needs no 3-D point: it fits the photo's pose to its 2-D - 2-D
matches with the registered photos (a generalized relative pose), asking for twice as many
inliers as a 2-D - 3-D registration. Its observations are then triangulated and the model
bundle-adjusted, as COLMAP's mapper does after any registration.
"""

from __future__ import annotations

from pathlib import Path

MIN_CORRESPONDENCES = 20  # matches to registered photos a photo needs to be tried (2 x LEFT_OUT's 10 inliers)


def register(pycolmap, database: Path, model, options) -> tuple[object | None, list[str]]:
    """The photos of `database` outside `model` (a pycolmap.Reconstruction, left as it is),
    placed by structure-less resectioning, most-matched first, in rounds while a round places
    one. options: the pipeline options (`poses.mapper_options`): the mapper's
    abs_pose_min_num_inliers (times two: inliers asked of a placed photo), the triangulation and
    the local and global bundle adjustment. Returns (a new model with them, their names) or
    (None, []) when none was placed. The model's frame is kept (no normalisation)."""
    db = pycolmap.Database.open(str(database))
    try:
        cache = pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions())
    finally:
        db.close()
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(pycolmap.Reconstruction(model))  # a copy: the model given stays whole
    grown, seen = mapper.reconstruction, mapper.observation_manager
    mapper_options, triangulation = options.get_mapper(), options.get_triangulation()
    placed: list[str] = []
    while True:
        waiting = [i for i, image in grown.images.items() if not image.has_pose
                   and seen.num_visible_correspondences(i) >= MIN_CORRESPONDENCES]
        waiting.sort(key=lambda i: (-seen.num_visible_correspondences(i), i))
        placed_now = 0
        for image_id in waiting:
            if not mapper.register_next_structure_less_image(mapper_options, image_id):
                if grown.images[image_id].has_pose:  # COLMAP leaves a photo whose pose refinement failed registered
                    seen.deregister_frame(grown.images[image_id].frame_id)
                continue
            mapper.triangulate_image(triangulation, image_id)
            mapper.iterative_local_refinement(options.ba_local_max_refinements,
                                              options.ba_local_max_refinement_change, mapper_options,
                                              options.get_local_bundle_adjustment(), triangulation, image_id)
            placed.append(grown.images[image_id].name)
            placed_now += 1
        if not placed_now:
            break
    if placed:
        mapper.iterative_global_refinement(options.ba_global_max_refinements,
                                           options.ba_global_max_refinement_change, mapper_options,
                                           options.get_global_bundle_adjustment(), triangulation,
                                           normalize_reconstruction=False)
    mapper.end_reconstruction(False)
    if not placed:
        return None, []
    grown.tear_down()  # the photos still out leave the model, as COLMAP's own models hold none
    return grown, placed
