"""Training data: the shared strong augmentation (:mod:`.augmentation`), background images
(:mod:`.backgrounds`), the pose dataset over object instances (:mod:`.pose_dataset`) and the
detection dataset over images (:mod:`.detection_dataset`). Typed items/batches live in
:mod:`cosy_lite.structures`."""
