"""Facts from the published OPC 40100-1 NodeSet (``Opc.Ua.MachineVision.NodeSet2.xml`` of the
OPC Foundation's UA-Nodeset collection, MachineVision, model version 1.0.0): the NodeIds,
browse names, node classes, type hierarchy, method arguments and structure layouts of the
nodes a Basic Vision System Server offers. Data only, written down from the NodeSet: the tests
compare the server's address space against them. A NodeId is ``("mv", i)`` in the Machine Vision
namespace or ``("ua", i)`` in namespace 0."""

from __future__ import annotations

NodeRef = tuple[str, int]

URI = "http://opcfoundation.org/UA/MachineVision"

# NodeId, browse name, node class, supertype
TYPES: list[tuple[int, str, str, NodeRef]] = [
    (1003, "VisionSystemType", "ObjectType", ("ua", 58)),
    (1017, "VisionStateMachineType", "ObjectType", ("ua", 2771)),
    (1021, "VisionAutomaticModeStateMachineType", "ObjectType", ("ua", 2771)),
    (1004, "RecipeManagementType", "ObjectType", ("ua", 58)),
    (1006, "ConfigurationManagementType", "ObjectType", ("ua", 58)),
    (1007, "ResultManagementType", "ObjectType", ("ua", 58)),
    (1024, "ResultReadyEventType", "ObjectType", ("ua", 2041)),
    (3017, "TrimmedString", "DataType", ("ua", 12)),
    (3018, "Handle", "DataType", ("ua", 7)),
    (3009, "ResultStateDataType", "DataType", ("ua", 6)),
    (3014, "TriStateBooleanDataType", "DataType", ("ua", 29)),
    (3019, "BinaryIdBaseDataType", "DataType", ("ua", 22)),
    (3008, "ConfigurationIdDataType", "DataType", ("mv", 3019)),
    (3002, "RecipeIdExternalDataType", "DataType", ("mv", 3019)),
    (3013, "RecipeIdInternalDataType", "DataType", ("mv", 3019)),
    (3016, "JobIdDataType", "DataType", ("ua", 22)),
    (3015, "MeasIdDataType", "DataType", ("ua", 22)),
    (3004, "PartIdDataType", "DataType", ("ua", 22)),
    (3003, "ProductIdDataType", "DataType", ("ua", 22)),
    (3021, "ResultIdDataType", "DataType", ("ua", 22)),
    (3005, "ProcessingTimesDataType", "DataType", ("ua", 22)),
    (3007, "ConfigurationDataType", "DataType", ("ua", 22)),
    (3006, "ResultDataType", "DataType", ("ua", 22)),
]
# the type it is declared on, NodeId, browse name, node class, type definition, data type,
# modelling rule (M mandatory, O optional, None: none)
DECLARATIONS: list[tuple[int, int, str, str, NodeRef | None, NodeRef | None, str | None]] = [
    (1003, 5004, "ConfigurationManagement", "Object", ("mv", 1006), None, "O"),
    (1003, 5015, "RecipeManagement", "Object", ("mv", 1004), None, "O"),
    (1003, 5020, "ResultManagement", "Object", ("mv", 1007), None, "O"),
    (1003, 5053, "VisionStateMachine", "Object", ("mv", 1017), None, "M"),
    (1017, 5024, "AutomaticModeStateMachine", "Object", ("mv", 1021), None, "O"),
    (1017, 5030, "Error", "Object", ("ua", 2307), None, None),
    (1017, 7094, "Halt", "Method", None, None, "M"),
    (1017, 5029, "Halted", "Object", ("ua", 2307), None, None),
    (1017, 5031, "Operational", "Object", ("ua", 2307), None, None),
    (1017, 5028, "Preoperational", "Object", ("ua", 2307), None, None),
    (1017, 7093, "Reset", "Method", None, None, "M"),
    (1017, 7095, "SelectModeAutomatic", "Method", None, None, "O"),
    (1021, 7097, "Abort", "Method", None, None, "M"),
    (1021, 5059, "ContinuousExecution", "Object", ("ua", 2307), None, None),
    (1021, 5056, "Initialized", "Object", ("ua", 2307), None, None),
    (1021, 5057, "Ready", "Object", ("ua", 2307), None, None),
    (1021, 5058, "SingleExecution", "Object", ("ua", 2307), None, None),
    (1021, 7009, "StartContinuous", "Method", None, None, "M"),
    (1021, 7098, "StartSingleJob", "Method", None, None, "M"),
    (1021, 7096, "Stop", "Method", None, None, "M"),
    (1004, 7013, "AddRecipe", "Method", None, None, "O"),
    (1004, 7014, "GetRecipeListFiltered", "Method", None, None, "M"),
    (1004, 7015, "PrepareRecipe", "Method", None, None, "M"),
    (1004, 7057, "RemoveRecipe", "Method", None, None, "O"),
    (1004, 7055, "UnprepareRecipe", "Method", None, None, "M"),
    (1006, 7048, "ActivateConfiguration", "Method", None, None, "M"),
    (1006, 6132, "ActiveConfiguration", "Variable", ("ua", 63), ("mv", 3007), "M"),
    (1006, 7041, "GetConfigurationById", "Method", None, None, "M"),
    (1006, 7045, "GetConfigurationList", "Method", None, None, "M"),
    (1007, 7026, "GetResultById", "Method", None, None, "M"),
    (1007, 7007, "GetResultComponentsById", "Method", None, None, "M"),
    (1007, 7089, "GetResultListFiltered", "Method", None, None, "M"),
    (1007, 7090, "ReleaseResultHandle", "Method", None, None, "O"),
    (1024, 6303, "CreationTime", "Variable", ("ua", 68), ("ua", 294), "M"),
    (1024, 6301, "ExternalRecipeId", "Variable", ("ua", 68), ("mv", 3002), "O"),
    (1024, 6142, "InternalConfigurationId", "Variable", ("ua", 68), ("mv", 3008), "M"),
    (1024, 6302, "InternalRecipeId", "Variable", ("ua", 68), ("mv", 3013), "M"),
    (1024, 6296, "IsPartial", "Variable", ("ua", 68), ("ua", 1), "M"),
    (1024, 6300, "JobId", "Variable", ("ua", 68), ("mv", 3016), "M"),
    (1024, 6299, "MeasId", "Variable", ("ua", 68), ("mv", 3015), "O"),
    (1024, 6304, "PartId", "Variable", ("ua", 68), ("mv", 3004), "O"),
    (1024, 6305, "ProcessingTimes", "Variable", ("ua", 68), ("mv", 3005), "O"),
    (1024, 6143, "ProductId", "Variable", ("ua", 68), ("mv", 3003), "O"),
    (1024, 6295, "ResultId", "Variable", ("ua", 68), ("mv", 3021), "M"),
    (1024, 6298, "ResultState", "Variable", ("ua", 68), ("mv", 3009), "M"),
]
# the methods' NodeIds on their types: input and output arguments (name, data type, rank)
ARGUMENTS: dict[int, tuple[tuple[tuple[str, NodeRef, int], ...], ...]] = {
    7094: (
        (
            ("Cause", ("ua", 6), -1),
            ("CauseDescription", ("ua", 12), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7093: (
        (
            ("Cause", ("ua", 6), -1),
            ("CauseDescription", ("ua", 12), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7095: (
        (
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7097: (
        (
            ("Cause", ("ua", 6), -1),
            ("CauseDescription", ("ua", 12), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7009: (
        (
            ("MeasId", ("mv", 3015), -1),
            ("PartId", ("mv", 3004), -1),
            ("RecipeId", ("mv", 3002), -1),
            ("ProductId", ("mv", 3003), -1),
            ("Parameters", ("ua", 24), 1),
        ),
        (
            ("JobId", ("mv", 3016), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7098: (
        (
            ("MeasId", ("mv", 3015), -1),
            ("PartId", ("mv", 3004), -1),
            ("RecipeId", ("mv", 3002), -1),
            ("ProductId", ("mv", 3003), -1),
            ("Parameters", ("ua", 24), 1),
        ),
        (
            ("JobId", ("mv", 3016), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7096: (
        (
            ("Cause", ("ua", 6), -1),
            ("CauseDescription", ("ua", 12), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7013: (
        (
            ("ExternalId", ("mv", 3002), -1),
            ("ProductId", ("mv", 3003), -1),
        ),
        (
            ("InternalId", ("mv", 3013), -1),
            ("Recipe", ("ua", 17), -1),
            ("Product", ("ua", 17), -1),
            ("TransferRequired", ("ua", 1), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7014: (
        (
            ("ExternalId", ("mv", 3002), -1),
            ("ProductId", ("mv", 3003), -1),
            ("IsPrepared", ("mv", 3014), -1),
            ("MaxResults", ("ua", 7), -1),
            ("StartIndex", ("ua", 7), -1),
            ("Timeout", ("ua", 6), -1),
        ),
        (
            ("IsComplete", ("ua", 1), -1),
            ("ResultCount", ("ua", 7), -1),
            ("RecipeHandle", ("mv", 3018), -1),
            ("RecipeList", ("mv", 3013), 1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7015: (
        (
            ("ExternalId", ("mv", 3002), -1),
            ("InternalIdIn", ("mv", 3013), -1),
        ),
        (
            ("InternalIdOut", ("mv", 3013), -1),
            ("IsCompleted", ("ua", 1), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7057: (
        (
            ("ExternalId", ("mv", 3002), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7055: (
        (
            ("ExternalId", ("mv", 3002), -1),
            ("InternalIdIn", ("mv", 3013), -1),
        ),
        (
            ("InternalIdOut", ("mv", 3013), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7048: (
        (
            ("InternalId", ("mv", 3008), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
    7041: (
        (
            ("InternalId", ("mv", 3008), -1),
            ("Timeout", ("ua", 6), -1),
        ),
        (
            ("ConfigurationHandle", ("mv", 3018), -1),
            ("Configuration", ("mv", 3007), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7045: (
        (
            ("MaxResults", ("ua", 7), -1),
            ("StartIndex", ("ua", 7), -1),
            ("Timeout", ("ua", 6), -1),
        ),
        (
            ("IsComplete", ("ua", 1), -1),
            ("ResultCount", ("ua", 7), -1),
            ("ConfigurationHandle", ("mv", 3018), -1),
            ("ConfigurationList", ("mv", 3007), 1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7026: (
        (
            ("ResultId", ("mv", 3021), -1),
            ("Timeout", ("ua", 6), -1),
        ),
        (
            ("ResultHandle", ("mv", 3018), -1),
            ("Result", ("mv", 3006), -1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7007: (
        (
            ("ResultId", ("mv", 3021), -1),
            ("Timeout", ("ua", 6), -1),
        ),
        (
            ("HasTransferableDataOnFile", ("ua", 1), -1),
            ("ResultHandle", ("mv", 3018), -1),
            ("IsPartial", ("ua", 1), -1),
            ("IsSimulated", ("ua", 1), -1),
            ("ResultState", ("mv", 3009), -1),
            ("MeasId", ("mv", 3015), -1),
            ("PartId", ("mv", 3004), -1),
            ("ExternalRecipeId", ("mv", 3002), -1),
            ("InternalRecipeId", ("mv", 3013), -1),
            ("ProductId", ("mv", 3003), -1),
            ("ExternalConfigurationId", ("mv", 3008), -1),
            ("InternalConfigurationId", ("mv", 3008), -1),
            ("JobId", ("mv", 3016), -1),
            ("CreationTime", ("ua", 294), -1),
            ("ProcessingTimes", ("mv", 3005), -1),
            ("ResultContent", ("ua", 24), 1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7089: (
        (
            ("ResultState", ("mv", 3009), -1),
            ("MeasId", ("mv", 3015), -1),
            ("PartId", ("mv", 3004), -1),
            ("ExternalRecipeId", ("mv", 3002), -1),
            ("InternalRecipeId", ("mv", 3013), -1),
            ("ExternalConfigurationId", ("mv", 3008), -1),
            ("InternalConfigurationId", ("mv", 3008), -1),
            ("ProductId", ("mv", 3003), -1),
            ("JobId", ("mv", 3016), -1),
            ("MaxResults", ("ua", 7), -1),
            ("StartIndex", ("ua", 7), -1),
            ("Timeout", ("ua", 6), -1),
        ),
        (
            ("IsComplete", ("ua", 1), -1),
            ("ResultCount", ("ua", 7), -1),
            ("ResultHandle", ("mv", 3018), -1),
            ("ResultList", ("mv", 3006), 1),
            ("Error", ("ua", 6), -1),
        ),
    ),
    7090: (
        (
            ("ResultHandle", ("mv", 3018), -1),
        ),
        (
            ("Error", ("ua", 6), -1),
        ),
    ),
}
# structures: the binary encoding's NodeId and the fields (name, data type, rank, optional)
STRUCTURES: dict[int, tuple[int, tuple[tuple[str, NodeRef, int, bool], ...]]] = {
    3019: (5027, (
        ("Id", ("mv", 3017), -1, False),
        ("Version", ("mv", 3017), -1, True),
        ("Hash", ("ua", 15), -1, True),
        ("HashAlgorithm", ("ua", 12), -1, True),
        ("Description", ("ua", 21), -1, True),
    )),
    3008: (5090, (
        ("Id", ("mv", 3017), -1, False),
        ("Version", ("mv", 3017), -1, True),
        ("Hash", ("ua", 15), -1, True),
        ("HashAlgorithm", ("ua", 12), -1, True),
        ("Description", ("ua", 21), -1, True),
    )),
    3002: (5002, (
        ("Id", ("mv", 3017), -1, False),
        ("Version", ("mv", 3017), -1, True),
        ("Hash", ("ua", 15), -1, True),
        ("HashAlgorithm", ("ua", 12), -1, True),
        ("Description", ("ua", 21), -1, True),
    )),
    3013: (5268, (
        ("Id", ("mv", 3017), -1, False),
        ("Version", ("mv", 3017), -1, True),
        ("Hash", ("ua", 15), -1, True),
        ("HashAlgorithm", ("ua", 12), -1, True),
        ("Description", ("ua", 21), -1, True),
    )),
    3016: (5008, (
        ("Id", ("mv", 3017), -1, False),
    )),
    3015: (5006, (
        ("Id", ("mv", 3017), -1, False),
        ("Description", ("ua", 21), -1, True),
    )),
    3004: (5013, (
        ("Id", ("mv", 3017), -1, False),
        ("Description", ("ua", 21), -1, True),
    )),
    3003: (5224, (
        ("Id", ("mv", 3017), -1, False),
        ("Description", ("ua", 21), -1, True),
    )),
    3021: (5274, (
        ("Id", ("mv", 3017), -1, False),
    )),
    3005: (5016, (
        ("StartTime", ("ua", 294), -1, False),
        ("EndTime", ("ua", 294), -1, False),
        ("AcquisitionDuration", ("ua", 290), -1, True),
        ("ProcessingDuration", ("ua", 290), -1, True),
    )),
    3007: (5088, (
        ("HasTransferableDataOnFile", ("ua", 1), -1, True),
        ("ExternalId", ("mv", 3008), -1, True),
        ("InternalId", ("mv", 3008), -1, False),
        ("LastModified", ("ua", 294), -1, False),
    )),
    3006: (5018, (
        ("ResultId", ("mv", 3021), -1, False),
        ("HasTransferableDataOnFile", ("ua", 1), -1, True),
        ("IsPartial", ("ua", 1), -1, False),
        ("IsSimulated", ("ua", 1), -1, True),
        ("ResultState", ("mv", 3009), -1, False),
        ("MeasId", ("mv", 3015), -1, True),
        ("PartId", ("mv", 3004), -1, True),
        ("ExternalRecipeId", ("mv", 3002), -1, True),
        ("InternalRecipeId", ("mv", 3013), -1, False),
        ("ProductId", ("mv", 3003), -1, True),
        ("ExternalConfigurationId", ("mv", 3008), -1, True),
        ("InternalConfigurationId", ("mv", 3008), -1, False),
        ("JobId", ("mv", 3016), -1, False),
        ("CreationTime", ("ua", 294), -1, False),
        ("ProcessingTimes", ("mv", 3005), -1, True),
        ("ResultContent", ("ua", 24), 1, True),
    )),
}
# the states: NodeId on their machine's type and StateNumber
STATES: dict[str, tuple[int, int]] = {
    "Preoperational": (5028, 1),
    "Halted": (5029, 2),
    "Error": (5030, 3),
    "Operational": (5031, 4),
    "Initialized": (5056, 5),
    "Ready": (5057, 6),
    "SingleExecution": (5058, 7),
    "ContinuousExecution": (5059, 8),
}
