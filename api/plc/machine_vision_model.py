"""The OPC 40100-1 (Machine Vision) information model a Basic Vision System Server needs, built
in the standard's namespace with the standard's NodeIds (those of the published
``Opc.Ua.MachineVision.NodeSet2.xml``, version 1.0.0).

The nodes are built here rather than imported from the NodeSet file at run time: the file is not
shipped by any Python package, and a server that needs a file the user must fetch first would
start without its Machine Vision model. Only what the facet's conformance units use is built
(``docs/plc.md`` lists it, and what is left out): the data types a client decodes (registered as
structures with their definitions, so ``load_data_type_definitions`` of any client reads them),
the object types with the instance declarations and methods of the state machines and of the
recipe, configuration and result management, and ``ResultReadyEventType`` with its fields.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.manage_nodes import create_encoding

URI = "http://opcfoundation.org/UA/MachineVision"

# data types
TRIMMED_STRING, HANDLE, RESULT_STATE = 3017, 3018, 3009
BINARY_ID_BASE = 3019
CONFIGURATION_ID, RECIPE_ID_EXTERNAL, RECIPE_ID_INTERNAL = 3008, 3002, 3013
JOB_ID, MEAS_ID, PART_ID, PRODUCT_ID, RESULT_ID = 3016, 3015, 3004, 3003, 3021
PROCESSING_TIMES, CONFIGURATION, RESULT = 3005, 3007, 3006
TRI_STATE_BOOLEAN = 3014
# object types
VISION_SYSTEM_TYPE, VISION_STATE_MACHINE_TYPE, AUTOMATIC_MODE_TYPE = 1003, 1017, 1021
RECIPE_MANAGEMENT_TYPE, CONFIGURATION_MANAGEMENT_TYPE, RESULT_MANAGEMENT_TYPE = 1004, 1006, 1007
RESULT_READY_EVENT_TYPE = 1024

MANDATORY, OPTIONAL = ua.ObjectIds.ModellingRule_Mandatory, ua.ObjectIds.ModellingRule_Optional


@dataclass(frozen=True)
class Struct:
    """A structure of the standard: its NodeId, encoding's NodeId and fields (name, data type
    (a number: in the standard's namespace; a NodeId: namespace 0), array, optional)."""

    name: str
    number: int
    binary_encoding: int
    fields: tuple[tuple[str, int | ua.NodeId, bool, bool], ...]
    base: int | None = None  # a structure of the standard it derives from
    abstract: bool = False


def node_id(number: int, ns: int = 0) -> ua.NodeId:
    """A numeric NodeId (asyncua's types spelled out for the type checker)."""
    return ua.NodeId(ua.Int32(number), ua.Int16(ns))


def _ns0(i: int) -> ua.NodeId:
    return node_id(i)


_ID_FIELDS: tuple[tuple[str, int | ua.NodeId, bool, bool], ...] = (
    ("Id", TRIMMED_STRING, False, False), ("Version", TRIMMED_STRING, False, True),
    ("Hash", _ns0(ua.ObjectIds.ByteString), False, True),
    ("HashAlgorithm", _ns0(ua.ObjectIds.String), False, True),
    ("Description", _ns0(ua.ObjectIds.LocalizedText), False, True))
_ID_AND_DESCRIPTION: tuple[tuple[str, int | ua.NodeId, bool, bool], ...] = (
    ("Id", TRIMMED_STRING, False, False),
    ("Description", _ns0(ua.ObjectIds.LocalizedText), False, True))
_UTC, _DURATION = _ns0(ua.ObjectIds.UtcTime), _ns0(ua.ObjectIds.Duration)
_BOOLEAN = _ns0(ua.ObjectIds.Boolean)

# in build order: a structure's field types come before it
STRUCTS: tuple[Struct, ...] = (
    Struct("BinaryIdBaseDataType", BINARY_ID_BASE, 5027, _ID_FIELDS, abstract=True),
    Struct("ConfigurationIdDataType", CONFIGURATION_ID, 5090, _ID_FIELDS, BINARY_ID_BASE),
    Struct("RecipeIdExternalDataType", RECIPE_ID_EXTERNAL, 5002, _ID_FIELDS, BINARY_ID_BASE),
    Struct("RecipeIdInternalDataType", RECIPE_ID_INTERNAL, 5268, _ID_FIELDS, BINARY_ID_BASE),
    Struct("JobIdDataType", JOB_ID, 5008, (("Id", TRIMMED_STRING, False, False),)),
    Struct("MeasIdDataType", MEAS_ID, 5006, _ID_AND_DESCRIPTION),
    Struct("PartIdDataType", PART_ID, 5013, _ID_AND_DESCRIPTION),
    Struct("ProductIdDataType", PRODUCT_ID, 5224, _ID_AND_DESCRIPTION),
    Struct("ResultIdDataType", RESULT_ID, 5274, (("Id", TRIMMED_STRING, False, False),)),
    Struct("ProcessingTimesDataType", PROCESSING_TIMES, 5016, (
        ("StartTime", _UTC, False, False), ("EndTime", _UTC, False, False),
        ("AcquisitionDuration", _DURATION, False, True),
        ("ProcessingDuration", _DURATION, False, True))),
    Struct("ConfigurationDataType", CONFIGURATION, 5088, (
        ("HasTransferableDataOnFile", _BOOLEAN, False, True),
        ("ExternalId", CONFIGURATION_ID, False, True),
        ("InternalId", CONFIGURATION_ID, False, False), ("LastModified", _UTC, False, False))),
    Struct("ResultDataType", RESULT, 5018, (
        ("ResultId", RESULT_ID, False, False),
        ("HasTransferableDataOnFile", _BOOLEAN, False, True),
        ("IsPartial", _BOOLEAN, False, False), ("IsSimulated", _BOOLEAN, False, True),
        ("ResultState", RESULT_STATE, False, False), ("MeasId", MEAS_ID, False, True),
        ("PartId", PART_ID, False, True), ("ExternalRecipeId", RECIPE_ID_EXTERNAL, False, True),
        ("InternalRecipeId", RECIPE_ID_INTERNAL, False, False),
        ("ProductId", PRODUCT_ID, False, True),
        ("ExternalConfigurationId", CONFIGURATION_ID, False, True),
        ("InternalConfigurationId", CONFIGURATION_ID, False, False),
        ("JobId", JOB_ID, False, False), ("CreationTime", _UTC, False, False),
        ("ProcessingTimes", PROCESSING_TIMES, False, True),
        ("ResultContent", _ns0(ua.ObjectIds.BaseDataType), True, True))),
)

# Arguments: (name, data type, array); a number is a data type of the standard's namespace
Arg = tuple[str, int | ua.NodeId, bool]
_I32, _U32 = _ns0(ua.ObjectIds.Int32), _ns0(ua.ObjectIds.UInt32)
_STRING, _NODE_ID = _ns0(ua.ObjectIds.String), _ns0(ua.ObjectIds.NodeId)
ERROR: Arg = ("Error", _I32, False)
_CAUSE: tuple[Arg, ...] = (("Cause", _I32, False), ("CauseDescription", _STRING, False))
_JOB_INPUTS: tuple[Arg, ...] = (
    ("MeasId", MEAS_ID, False), ("PartId", PART_ID, False),
    ("RecipeId", RECIPE_ID_EXTERNAL, False), ("ProductId", PRODUCT_ID, False),
    ("Parameters", _ns0(ua.ObjectIds.BaseDataType), True))


@dataclass(frozen=True)
class Method:
    """A method of a type of the standard: NodeId on its type, browse name, arguments."""

    number: int
    name: str
    inputs: tuple[Arg, ...]
    outputs: tuple[Arg, ...]
    rule: int = MANDATORY


METHODS: dict[int, tuple[Method, ...]] = {
    VISION_STATE_MACHINE_TYPE: (
        Method(7094, "Halt", _CAUSE, (ERROR,)), Method(7093, "Reset", _CAUSE, (ERROR,)),
        Method(7095, "SelectModeAutomatic", (), (ERROR,), OPTIONAL)),
    AUTOMATIC_MODE_TYPE: (
        Method(7098, "StartSingleJob", _JOB_INPUTS, (("JobId", JOB_ID, False), ERROR)),
        Method(7009, "StartContinuous", _JOB_INPUTS, (("JobId", JOB_ID, False), ERROR)),
        Method(7096, "Stop", _CAUSE, (ERROR,)), Method(7097, "Abort", _CAUSE, (ERROR,))),
    RECIPE_MANAGEMENT_TYPE: (
        Method(7013, "AddRecipe", (("ExternalId", RECIPE_ID_EXTERNAL, False),
                                   ("ProductId", PRODUCT_ID, False)),
               (("InternalId", RECIPE_ID_INTERNAL, False), ("Recipe", _NODE_ID, False),
                ("Product", _NODE_ID, False),
                ("TransferRequired", _BOOLEAN, False), ERROR), OPTIONAL),
        Method(7014, "GetRecipeListFiltered", (
            ("ExternalId", RECIPE_ID_EXTERNAL, False), ("ProductId", PRODUCT_ID, False),
            ("IsPrepared", TRI_STATE_BOOLEAN, False), ("MaxResults", _U32, False),
            ("StartIndex", _U32, False), ("Timeout", _I32, False)), (
            ("IsComplete", _BOOLEAN, False), ("ResultCount", _U32, False),
            ("RecipeHandle", HANDLE, False), ("RecipeList", RECIPE_ID_INTERNAL, True), ERROR)),
        Method(7015, "PrepareRecipe", (("ExternalId", RECIPE_ID_EXTERNAL, False),
                                       ("InternalIdIn", RECIPE_ID_INTERNAL, False)),
               (("InternalIdOut", RECIPE_ID_INTERNAL, False), ("IsCompleted", _BOOLEAN, False),
                ERROR)),
        Method(7055, "UnprepareRecipe", (("ExternalId", RECIPE_ID_EXTERNAL, False),
                                         ("InternalIdIn", RECIPE_ID_INTERNAL, False)),
               (("InternalIdOut", RECIPE_ID_INTERNAL, False), ERROR)),
        Method(7057, "RemoveRecipe", (("ExternalId", RECIPE_ID_EXTERNAL, False),), (ERROR,),
               OPTIONAL)),
    CONFIGURATION_MANAGEMENT_TYPE: (
        Method(7048, "ActivateConfiguration", (("InternalId", CONFIGURATION_ID, False),),
               (ERROR,)),
        Method(7041, "GetConfigurationById", (("InternalId", CONFIGURATION_ID, False),
                                              ("Timeout", _I32, False)),
               (("ConfigurationHandle", HANDLE, False),
                ("Configuration", CONFIGURATION, False), ERROR)),
        Method(7045, "GetConfigurationList", (("MaxResults", _U32, False),
                                              ("StartIndex", _U32, False),
                                              ("Timeout", _I32, False)),
               (("IsComplete", _BOOLEAN, False), ("ResultCount", _U32, False),
                ("ConfigurationHandle", HANDLE, False),
                ("ConfigurationList", CONFIGURATION, True), ERROR))),
    RESULT_MANAGEMENT_TYPE: (
        Method(7026, "GetResultById", (("ResultId", RESULT_ID, False), ("Timeout", _I32, False)),
               (("ResultHandle", HANDLE, False), ("Result", RESULT, False), ERROR)),
        Method(7007, "GetResultComponentsById", (("ResultId", RESULT_ID, False),
                                                 ("Timeout", _I32, False)), (
            ("HasTransferableDataOnFile", _BOOLEAN, False), ("ResultHandle", HANDLE, False),
            ("IsPartial", _BOOLEAN, False), ("IsSimulated", _BOOLEAN, False),
            ("ResultState", RESULT_STATE, False), ("MeasId", MEAS_ID, False),
            ("PartId", PART_ID, False), ("ExternalRecipeId", RECIPE_ID_EXTERNAL, False),
            ("InternalRecipeId", RECIPE_ID_INTERNAL, False), ("ProductId", PRODUCT_ID, False),
            ("ExternalConfigurationId", CONFIGURATION_ID, False),
            ("InternalConfigurationId", CONFIGURATION_ID, False), ("JobId", JOB_ID, False),
            ("CreationTime", _UTC, False), ("ProcessingTimes", PROCESSING_TIMES, False),
            ("ResultContent", _ns0(ua.ObjectIds.BaseDataType), True), ERROR)),
        Method(7089, "GetResultListFiltered", (
            ("ResultState", RESULT_STATE, False), ("MeasId", MEAS_ID, False),
            ("PartId", PART_ID, False), ("ExternalRecipeId", RECIPE_ID_EXTERNAL, False),
            ("InternalRecipeId", RECIPE_ID_INTERNAL, False),
            ("ExternalConfigurationId", CONFIGURATION_ID, False),
            ("InternalConfigurationId", CONFIGURATION_ID, False),
            ("ProductId", PRODUCT_ID, False), ("JobId", JOB_ID, False),
            ("MaxResults", _U32, False), ("StartIndex", _U32, False), ("Timeout", _I32, False)),
               (("IsComplete", _BOOLEAN, False), ("ResultCount", _U32, False),
                ("ResultHandle", HANDLE, False), ("ResultList", RESULT, True), ERROR)),
        Method(7090, "ReleaseResultHandle", (("ResultHandle", HANDLE, False),), (ERROR,),
               OPTIONAL)),
}

# the states of the two state machines: name -> (NodeId on the type, StateNumber)
STATES: dict[int, dict[str, tuple[int, int]]] = {
    VISION_STATE_MACHINE_TYPE: {"Preoperational": (5028, 1), "Halted": (5029, 2),
                                "Error": (5030, 3), "Operational": (5031, 4)},
    AUTOMATIC_MODE_TYPE: {"Initialized": (5056, 5), "Ready": (5057, 6),
                          "SingleExecution": (5058, 7), "ContinuousExecution": (5059, 8)},
}

# the components of the types that hold other types: (type, NodeId, browse name, its type, rule)
COMPONENTS: tuple[tuple[int, int, str, int, int], ...] = (
    (VISION_SYSTEM_TYPE, 5053, "VisionStateMachine", VISION_STATE_MACHINE_TYPE, MANDATORY),
    (VISION_SYSTEM_TYPE, 5004, "ConfigurationManagement", CONFIGURATION_MANAGEMENT_TYPE,
     OPTIONAL),
    (VISION_SYSTEM_TYPE, 5015, "RecipeManagement", RECIPE_MANAGEMENT_TYPE, OPTIONAL),
    (VISION_SYSTEM_TYPE, 5020, "ResultManagement", RESULT_MANAGEMENT_TYPE, OPTIONAL),
    (VISION_STATE_MACHINE_TYPE, 5024, "AutomaticModeStateMachine", AUTOMATIC_MODE_TYPE,
     OPTIONAL),
)

# ResultReadyEventType's fields: (NodeId, browse name, data type, mandatory)
RESULT_READY_FIELDS: tuple[tuple[int, str, int | ua.NodeId, bool], ...] = (
    (6303, "CreationTime", _UTC, True), (6142, "InternalConfigurationId", CONFIGURATION_ID, True),
    (6302, "InternalRecipeId", RECIPE_ID_INTERNAL, True), (6296, "IsPartial", _BOOLEAN, True),
    (6300, "JobId", JOB_ID, True), (6295, "ResultId", RESULT_ID, True),
    (6298, "ResultState", RESULT_STATE, True), (6299, "MeasId", MEAS_ID, False),
    (6304, "PartId", PART_ID, False), (6143, "ProductId", PRODUCT_ID, False),
    (6301, "ExternalRecipeId", RECIPE_ID_EXTERNAL, False),
    (6305, "ProcessingTimes", PROCESSING_TIMES, False),
)


class Model:
    """The standard's nodes in one server: its namespace index, NodeIds and structure classes."""

    def __init__(self, server: Server, ns: int) -> None:
        self.server = server
        self.ns = ns
        self.classes: dict[str, type[Any]] = {}

    def id(self, number: int) -> ua.NodeId:
        return node_id(number, self.ns)

    def name(self, text: str) -> ua.QualifiedName:
        return ua.QualifiedName(text, self.ns)

    def data_type(self, t: int | ua.NodeId) -> ua.NodeId:
        return t if isinstance(t, ua.NodeId) else self.id(t)

    def new(self, struct: str, **values: Any) -> Any:
        """A value of one of the standard's structures."""
        out = self.classes[struct]()
        for key, value in values.items():
            setattr(out, key, value)
        return out

    def argument(self, arg: Arg) -> ua.Argument:
        name, dtype, array = arg
        a = ua.Argument()
        a.Name = name
        a.DataType = self.data_type(dtype)
        a.ValueRank = 1 if array else -1
        a.ArrayDimensions = [0] if array else []
        return a

    async def rule(self, node: Node, rule: int) -> None:
        await node.add_reference(node_id(rule), ua.ObjectIds.HasModellingRule, forward=True)


async def build_model(server: Server) -> Model:
    """The standard's namespace, data types, object types and event type in ``server``."""
    model = Model(server, await server.register_namespace(URI))
    await _data_types(model)
    await _object_types(model)
    await _event_types(model)
    return model


def register_aliases(ns: int) -> None:
    """``TrimmedString`` and ``Handle`` as the built-in types they restrict, for asyncua's
    decoders: namespace 0 has types of these names too, so asyncua (2.1) takes the standard's
    for known and leaves them out of its table of aliases. A client on asyncua needs the same
    before ``load_data_type_definitions`` (``ns``: the Machine Vision namespace's index)."""
    ua.basetype_by_datatype[node_id(TRIMMED_STRING, ns)] = "String"
    ua.basetype_by_datatype[node_id(HANDLE, ns)] = "UInt32"


async def _data_types(model: Model) -> None:
    server = model.server
    for number, name, builtin in ((TRIMMED_STRING, "TrimmedString", ua.ObjectIds.String),
                                  (HANDLE, "Handle", ua.ObjectIds.UInt32),
                                  (RESULT_STATE, "ResultStateDataType", ua.ObjectIds.Int32)):
        await server.get_node(node_id(builtin)).add_data_type(model.id(number),
                                                              model.name(name))
    register_aliases(model.ns)
    tri = await server.get_node(node_id(ua.ObjectIds.Enumeration)).add_data_type(
        model.id(TRI_STATE_BOOLEAN), model.name("TriStateBooleanDataType"))
    edef = ua.EnumDefinition()
    for value, label in enumerate(("FALSE", "TRUE", "DONTCARE")):
        choice = ua.EnumField()
        choice.Name, choice.Value = label, value
        choice.DisplayName = ua.LocalizedText(label)
        edef.Fields.append(choice)
    await tri.write_data_type_definition(edef)
    for struct in STRUCTS:
        base = model.id(struct.base) if struct.base is not None \
            else node_id(ua.ObjectIds.Structure)
        node = await server.get_node(base).add_data_type(model.id(struct.number),
                                                         model.name(struct.name))
        if struct.abstract:
            await node.write_attribute(ua.AttributeIds.IsAbstract,
                                       ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
        encoding = await create_encoding(node, model.id(struct.binary_encoding),
                                         ua.QualifiedName("Default Binary", 0))
        sdef = ua.StructureDefinition()
        sdef.BaseDataType = base
        sdef.DefaultEncodingId = encoding.nodeid
        sdef.StructureType = ua.StructureType.StructureWithOptionalFields \
            if any(optional for *_, optional in struct.fields) else ua.StructureType.Structure
        for fname, ftype, array, optional in struct.fields:
            field = ua.StructureField()
            field.Name, field.DataType = fname, model.data_type(ftype)
            field.ValueRank = 1 if array else -1
            field.ArrayDimensions = [0] if array else []
            field.IsOptional = optional
            sdef.Fields.append(field)
        await node.write_data_type_definition(sdef)
    loaded = await server.load_data_type_definitions()
    # asyncua registers each structure's class in ``ua`` once per process; a second server in
    # the same process (tests) finds them there instead of in the returned dict
    model.classes = {s.name: loaded.get(s.name) or getattr(ua, s.name)
                     for s in STRUCTS if not s.abstract}


async def _object_types(model: Model) -> None:
    server = model.server
    base = server.get_node(node_id(ua.ObjectIds.BaseObjectType))
    fsm = server.get_node(node_id(ua.ObjectIds.FiniteStateMachineType))
    types: dict[int, Node] = {}
    for number, name, parent in (
            (VISION_SYSTEM_TYPE, "VisionSystemType", base),
            (VISION_STATE_MACHINE_TYPE, "VisionStateMachineType", fsm),
            (AUTOMATIC_MODE_TYPE, "VisionAutomaticModeStateMachineType", fsm),
            (RECIPE_MANAGEMENT_TYPE, "RecipeManagementType", base),
            (CONFIGURATION_MANAGEMENT_TYPE, "ConfigurationManagementType", base),
            (RESULT_MANAGEMENT_TYPE, "ResultManagementType", base)):
        types[number] = await parent.add_object_type(model.id(number), model.name(name))
    # components added bottom-up, so a component's own instance declarations exist first
    for owner, number, name, of_type, rule in reversed(COMPONENTS):
        node = await types[owner].add_object(model.id(number), model.name(name),
                                             model.id(of_type), instantiate_optional=False)
        await model.rule(node, rule)
    for owner, methods in METHODS.items():
        for m in methods:
            node = await types[owner].add_method(
                model.id(m.number), model.name(m.name), None,
                [model.argument(a) for a in m.inputs], [model.argument(a) for a in m.outputs])
            await model.rule(node, m.rule)
    for owner, states in STATES.items():
        for name, (number, state_number) in states.items():
            state = await types[owner].add_object(model.id(number), model.name(name),
                                                  ua.ObjectIds.StateType)
            await (await state.get_child("0:StateNumber")).write_value(
                ua.Variant(state_number, ua.VariantType.UInt32))
    active = await types[CONFIGURATION_MANAGEMENT_TYPE].add_variable(
        model.id(6132), model.name("ActiveConfiguration"),
        ua.Variant(model.new("ConfigurationDataType"), ua.VariantType.ExtensionObject),
        datatype=model.id(CONFIGURATION))
    await model.rule(active, MANDATORY)


async def _event_types(model: Model) -> None:
    server = model.server
    ready = await server.get_node(node_id(ua.ObjectIds.BaseEventType)).add_object_type(
        model.id(RESULT_READY_EVENT_TYPE), model.name("ResultReadyEventType"))
    for number, name, dtype, mandatory in RESULT_READY_FIELDS:
        prop = await ready.add_property(model.id(number), model.name(name),
                                        _default(model, dtype), datatype=model.data_type(dtype))
        await model.rule(prop, MANDATORY if mandatory else OPTIONAL)


def _default(model: Model, dtype: int | ua.NodeId) -> ua.Variant:
    """An event field's value before the first event (asyncua's event object copies it)."""
    if isinstance(dtype, ua.NodeId):
        if dtype == _UTC:
            return ua.Variant(ua.get_win_epoch(), ua.VariantType.DateTime)
        return ua.Variant(False, ua.VariantType.Boolean)
    if dtype == RESULT_STATE:
        return ua.Variant(0, ua.VariantType.Int32)
    name = next(s.name for s in STRUCTS if s.number == dtype)
    return ua.Variant(model.new(name), ua.VariantType.ExtensionObject)
