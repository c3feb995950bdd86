// A Machine Vision (OPC 40100-1) client on another stack than the server's (node-opcua): finds
// the object whose type is VisionSystemType, selects automatic mode, prepares a recipe by its
// external id, starts a single job, waits for its ResultReadyEvent and reads the result with
// GetResultById; every id goes as the standard's structure, built from the server's data type
// definitions. Prints one JSON line:
// {"facts": {checked, mismatches}, "jobId", "prepared", "event": {jobId, resultId, resultState},
//  "result": {jobId, resultState, measId, position_mm, rotvec_rad}}.
// FACTS is a JSON file of [namespace ("mv" or "ua"), numeric id, browse name, node class] rows
// from the published NodeSet; each node's BrowseName and NodeClass are read and compared.
// Usage: node node_opcua_machine_vision.js ENDPOINT USER PASSWORD RECIPE FACTS
const opcua = require("node-opcua");

const MV = "http://opcfoundation.org/UA/MachineVision";

// a field of a decoded structure (node-opcua spells field names in lower camel case)
const field = (obj, name) =>
  obj[name] !== undefined ? obj[name] : obj[name[0].toLowerCase() + name.slice(1)];

async function main() {
  const [endpoint, user, password, recipe, factsPath] = process.argv.slice(2);
  const client = opcua.OPCUAClient.create({
    endpointMustExist: false,
    securityMode: opcua.MessageSecurityMode.None,
    securityPolicy: opcua.SecurityPolicy.None,
    connectionStrategy: { maxRetry: 2, initialDelay: 200 },
  });
  await client.connect(endpoint);
  const session = await client.createSession({
    type: opcua.UserTokenType.UserName, userName: user, password });
  const namespaces = (await session.read({
    nodeId: "ns=0;i=2255", attributeId: opcua.AttributeIds.Value })).value.value;
  const mv = namespaces.indexOf(MV);
  if (mv < 0) throw new Error(`no namespace ${MV}`);
  const typeId = (i) => opcua.resolveNodeId(`ns=${mv};i=${i}`);

  // every node of the facts table by its NodeId: its browse name and node class
  const facts = JSON.parse(require("fs").readFileSync(factsPath, "utf8"));
  const factIds = facts.map(([ns, i]) => opcua.resolveNodeId(`ns=${ns === "mv" ? mv : 0};i=${i}`));
  const names = await session.read(factIds.map((nodeId) => ({
    nodeId, attributeId: opcua.AttributeIds.BrowseName })));
  const classes = await session.read(factIds.map((nodeId) => ({
    nodeId, attributeId: opcua.AttributeIds.NodeClass })));
  const mismatches = [];
  facts.forEach(([ns, i, name, nodeClass], k) => {
    const got = names[k].value.value;
    const gotName = got ? got.name : null;
    const gotNs = got ? got.namespaceIndex : null;
    const gotClass = opcua.NodeClass[classes[k].value.value];
    if (gotName !== name || gotClass !== nodeClass || gotNs !== (ns === "mv" ? mv : 0)) {
      mismatches.push({ node: `${ns}:${i}`, want: [name, nodeClass], got: [gotName, gotClass] });
    }
  });

  const objects = await session.browse({
    nodeId: "ns=0;i=85", browseDirection: opcua.BrowseDirection.Forward,
    resultMask: 63 });
  const vsRef = objects.references.find(
    (r) => r.typeDefinition.toString() === typeId(1003).toString());
  if (!vsRef) throw new Error("no object of VisionSystemType under Objects");
  const child = async (nodeId, name) => {
    const path = await session.translateBrowsePath(opcua.makeBrowsePath(
      nodeId, `/${mv}:${name}`));
    if (!path.targets || !path.targets.length) throw new Error(`no ${name}`);
    return path.targets[0].targetId;
  };
  const vs = vsRef.nodeId;
  const sm = await child(vs, "VisionStateMachine");
  const auto = await child(sm, "AutomaticModeStateMachine");
  const recipes = await child(vs, "RecipeManagement");
  const results = await child(vs, "ResultManagement");
  const struct = async (i, pojo) => ({
    dataType: opcua.DataType.ExtensionObject,
    value: await session.constructExtensionObject(typeId(i), pojo) });
  const call = async (objectId, name, inputArguments) => {
    const res = await session.call({
      objectId, methodId: await child(objectId, name), inputArguments });
    if (res.statusCode.isNotGood()) throw new Error(`${name}: ${res.statusCode.toString()}`);
    const out = res.outputArguments.map((v) => v.value);
    if (out[out.length - 1] !== 0) throw new Error(`${name}: Error ${out[out.length - 1]}`);
    return out;
  };

  // ResultReadyEvents from the VisionSystem object
  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50, publishingEnabled: true,
    requestedMaxKeepAliveCount: 20, requestedLifetimeCount: 600 });
  const fields = ["EventType", `${mv}:JobId`, `${mv}:ResultId`, `${mv}:ResultState`];
  const item = await subscription.monitor(
    { nodeId: vs, attributeId: opcua.AttributeIds.EventNotifier },
    { queueSize: 100, filter: opcua.constructEventFilter(fields) },
    opcua.TimestampsToReturn.Both);
  const events = [];
  item.on("changed", (values) => {
    if (values[0].value.toString() !== typeId(1024).toString()) return;
    events.push({ jobId: field(values[1].value, "Id"), resultId: field(values[2].value, "Id"),
                  resultState: values[3].value });
  });

  await call(sm, "SelectModeAutomatic", []);
  const [internal] = await call(recipes, "PrepareRecipe", [
    await struct(3002, { id: recipe }), await struct(3013, { id: "" })]);
  const [jobIdOut] = await call(auto, "StartSingleJob", [
    await struct(3015, { id: "node-meas" }), await struct(3004, { id: "node-part" }),
    await struct(3002, { id: "" }), await struct(3003, { id: "" }),
    { dataType: opcua.DataType.Variant, arrayType: opcua.VariantArrayType.Array, value: [] }]);
  const jobId = field(jobIdOut, "Id");
  const deadline = Date.now() + 60000;
  while (!events.some((e) => e.jobId === jobId)) {
    if (Date.now() > deadline) throw new Error(`no ResultReadyEvent for ${jobId}`);
    await new Promise((ok) => setTimeout(ok, 50));
  }
  const [, result] = await call(results, "GetResultById", [
    await struct(3021, { id: `r-${jobId}` }), { dataType: opcua.DataType.Int32, value: 0 }]);
  const pose = field(result, "ResultContent")[0].value;
  console.log(JSON.stringify({
    facts: { checked: facts.length, mismatches },
    jobId, prepared: field(internal, "Id"),
    event: events.find((e) => e.jobId === jobId),
    result: { jobId: field(field(result, "JobId"), "Id"),
              resultState: field(result, "ResultState"),
              measId: field(field(result, "MeasId"), "Id"),
              position_mm: Array.from(field(pose, "position_mm")),
              rotvec_rad: Array.from(field(pose, "rotvec_rad")) } }));
  await subscription.terminate();
  await session.close();
  await client.disconnect();
}

main().catch((err) => { console.error(String(err && err.stack || err)); process.exit(1); });
