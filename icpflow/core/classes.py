"""The object classes of the project's frame pairs: a pair's ``classes`` field holds an Argoverse 2 category index
+ 1 (0 = none, :data:`AV2_CATEGORIES`), which every reader converts into and the metrics group into AV2's bucketed
meta-classes (:data:`AV2_META`)."""

# AV2 categories (flow_labels `classes` = av2 category index + 1, 0 = none) -> bucketed meta-classes, as in
# bucketed-scene-flow-eval 2.0.25 (ANIMAL, DOG and road-sign categories belong to no meta-class).
AV2_CATEGORIES = (
    "ANIMAL",
    "ARTICULATED_BUS",
    "BICYCLE",
    "BICYCLIST",
    "BOLLARD",
    "BOX_TRUCK",
    "BUS",
    "CONSTRUCTION_BARREL",
    "CONSTRUCTION_CONE",
    "DOG",
    "LARGE_VEHICLE",
    "MESSAGE_BOARD_TRAILER",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN",
    "MOTORCYCLE",
    "MOTORCYCLIST",
    "OFFICIAL_SIGNALER",
    "PEDESTRIAN",
    "RAILED_VEHICLE",
    "REGULAR_VEHICLE",
    "SCHOOL_BUS",
    "SIGN",
    "STOP_SIGN",
    "STROLLER",
    "TRAFFIC_LIGHT_TRAILER",
    "TRUCK",
    "TRUCK_CAB",
    "VEHICULAR_TRAILER",
    "WHEELCHAIR",
    "WHEELED_DEVICE",
    "WHEELED_RIDER",
)
META_CLASSES = ("BACKGROUND", "CAR", "OTHER_VEHICLES", "PEDESTRIAN", "WHEELED_VRU")
_META_MEMBERS = {
    "CAR": ("REGULAR_VEHICLE",),
    "OTHER_VEHICLES": (
        "BOX_TRUCK",
        "LARGE_VEHICLE",
        "RAILED_VEHICLE",
        "TRUCK",
        "TRUCK_CAB",
        "VEHICULAR_TRAILER",
        "ARTICULATED_BUS",
        "BUS",
        "SCHOOL_BUS",
    ),
    "PEDESTRIAN": ("PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"),
    "WHEELED_VRU": ("BICYCLE", "BICYCLIST", "MOTORCYCLE", "MOTORCYCLIST", "WHEELED_DEVICE", "WHEELED_RIDER"),
}
AV2_META = {0: "BACKGROUND"} | {
    AV2_CATEGORIES.index(name) + 1: meta for meta, names in _META_MEMBERS.items() for name in names
}
