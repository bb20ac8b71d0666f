"""A user's own photos in the native dataset format (``python -m apps.prepare``, docs/photos.md).

One module per job: :mod:`~apps.photo.images` (reading photos and their EXIF focal length),
:mod:`~apps.photo.faces` (mediapipe face detection and the 478-point mesh), :mod:`~apps.photo.landmarks68`
(the mesh's iBUG-68 landmarks, iris centres and eyelid contours), :mod:`~apps.photo.face_model` (the 3D head
the photo is fitted with), :mod:`~apps.photo.head_pose` (PnP and the head scale), :mod:`~apps.photo.normalize`
(ETH-XGaze-style normalization: the camera, the warp, the crop), :mod:`~apps.photo.masks` (head and eye masks),
:mod:`~apps.photo.gaze` (the gaze from the iris), :mod:`~apps.photo.rows` (one face as a row of a subject file),
:mod:`~apps.photo.labels` (a labels CSV of gazes), :mod:`~apps.photo.sheet` (the contact sheet) and
:mod:`~apps.photo.paste` (a redirected crop pasted back into its photo).

Pixel convention everywhere: u = 0 is the left edge of column 0 (pixel centres at k + 0.5), as docs/data.md.
"""
