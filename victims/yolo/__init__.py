"""YOLO-style 2D detectors (YOLOv3 objectness semantics): the CPU-sized mini-YOLO of §2.3 and the
yolov3-tiny / YOLOv3 layouts, loss, anchors, decoding and NMS."""
