"""Camera files in the ecosystem's formats, one module per format.

Each module reads a file's text into a ``rectify.user_camera.Camera`` (K 3x3 px and the image size
(width, height) px in OpenCV's pixel convention, and OpenCV's distortion coefficients) and
writes one back. ``formats.camera_file`` is the front door: it reads the file, tells the format
from its content and picks a camera out of a multi-camera file. Specified in
``models_spec/camera-files.md``.

* ``json_file``: dimenet's own ``camera.json``.
* ``opencv``: OpenCV FileStorage YAML and XML (``!!opencv-matrix``), through ``cv2.FileStorage``.
* ``ros``: ROS ``camera_info`` YAML (camera_calibration_parsers).
* ``colmap``: COLMAP ``cameras.txt`` (its pixel centres are 0.5 px off OpenCV's).
* ``kalibr``: Kalibr camchain YAML.
* ``mrcal``: mrcal ``.cameramodel``.
* ``values``: the checks and helpers they share.
"""
