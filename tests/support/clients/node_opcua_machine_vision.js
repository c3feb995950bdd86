// A Machine Vision (OPC 40100-1) client on another stack than the server's (node-opcua): reads
// every fact of the published NodeSet's table by the standard's NodeIds (browse names, node
// classes, method arguments, state numbers, structure layouts), finds the object whose type is
// VisionSystemType, selects automatic mode, and for each recipe prepares it by its external
// id, starts a single job, waits for its ResultReadyEvent and reads the result with
// GetResultById; every id goes as the standard's structure, built from the server's data type
// definitions. Prints one JSON line:
// {"facts": {checked, mismatches}, "jobs": [{"jobId", "prepared", "event": {jobId, resultId,
//  resultState}, "result": {jobId, resultState, measId, position_mm, rotvec_rad}}, ...]}.
// FACTS is a JSON file {"nodes": [[ns, i, browse name, node class]], "arguments": [[i, [[name,
// [ns, i], rank]], [...]]], "states": [[name, i, number]], "structures": [[i, [ns, encoding],
// [[name, [ns, i], rank, optional]]]]} from the published NodeSet (ns "mv" or "ua").
// Usage: node node_opcua_machine_vision.js ENDPOINT USER PASSWORD RECIPE[,RECIPE...] FACTS
const opcua = require("node-opcua");

const MV = "http://opcfoundation.org/UA/MachineVision";

// a field of a decoded structure (node-opcua spells field names in lower camel case)
const field = (obj, name) =>
  obj[name] !== undefined ? obj[name] : obj[name[0].toLowerCase() + name.slice(1)];

async function main() {
  const [endpoint, user, password, recipeList, factsPath] = process.argv.slice(2);
  const recipeIds = recipeList.split(",");
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

  const ref = ([ns, i]) => opcua.resolveNodeId(`ns=${ns === "mv" ? mv : 0};i=${i}`);
  const same = (a, b) => a.toString() === b.toString();
  const facts = JSON.parse(require("fs").readFileSync(factsPath, "utf8"));
  const mismatches = [];
  let checked = 0;
  const childOf = async (nodeId, name) => {
    const path = await session.translateBrowsePath(opcua.makeBrowsePath(nodeId, `/${name}`));
    return path.targets && path.targets.length ? path.targets[0].targetId : null;
  };
  const value = async (nodeId) =>
    (await session.read({ nodeId, attributeId: opcua.AttributeIds.Value })).value.value;

  // every node by its NodeId: its browse name and node class
  const ids = facts.nodes.map(([ns, i]) => ref([ns, i]));
  const names = await session.read(ids.map((nodeId) => ({
    nodeId, attributeId: opcua.AttributeIds.BrowseName })));
  const classes = await session.read(ids.map((nodeId) => ({
    nodeId, attributeId: opcua.AttributeIds.NodeClass })));
  facts.nodes.forEach(([ns, i, name, nodeClass], k) => {
    const got = names[k].value.value;
    const gotName = got ? got.name : null;
    const gotNs = got ? got.namespaceIndex : null;
    const gotClass = opcua.NodeClass[classes[k].value.value];
    if (gotName !== name || gotClass !== nodeClass || gotNs !== (ns === "mv" ? mv : 0)) {
      mismatches.push({ node: `${ns}:${i}`, want: [name, nodeClass], got: [gotName, gotClass] });
    }
    checked += 1;
  });
  // every method's input and output arguments: name, data type, value rank
  for (const [i, lists] of facts.arguments) {
    const method = ref(["mv", i]);
    for (const [k, property] of ["InputArguments", "OutputArguments"].entries()) {
      const node = await childOf(method, property);
      const got = node ? (await value(node)) || [] : [];
      const want = lists[k];
      const ok = got.length === want.length && want.every(([name, type, rank], j) =>
        got[j].name === name && same(got[j].dataType, ref(type)) && got[j].valueRank === rank);
      if (!ok) {
        mismatches.push({ node: `mv:${i}.${property}`, want,
                          got: got.map((a) => [a.name, a.dataType.toString(), a.valueRank]) });
      }
    }
    checked += 1;
  }
  // every state of the two machines: its StateNumber
  for (const [name, i, number] of facts.states) {
    const node = await childOf(ref(["mv", i]), "StateNumber");
    const got = node ? await value(node) : null;
    if (got !== number) mismatches.push({ node: `mv:${i}`, want: [name, number], got });
    checked += 1;
  }
  // every structure's definition: its binary encoding and its fields
  for (const [i, encoding, fields] of facts.structures) {
    const sdef = (await session.read({
      nodeId: ref(["mv", i]), attributeId: opcua.AttributeIds.DataTypeDefinition })).value.value;
    const got = sdef && sdef.fields ? sdef.fields : [];
    const ok = sdef && same(sdef.defaultEncodingId, ref(encoding))
      && got.length === fields.length && fields.every(([name, type, rank, optional], j) =>
        got[j].name === name && same(got[j].dataType, ref(type))
        && got[j].valueRank === rank && Boolean(got[j].isOptional) === optional);
    if (!ok) {
      mismatches.push({ node: `mv:${i}`, want: fields, got: got.map((f) => [
        f.name, f.dataType.toString(), f.valueRank, Boolean(f.isOptional)]) });
    }
    checked += 1;
  }

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
  const jobs = [];
  for (const [k, recipe] of recipeIds.entries()) {
    const [internal] = await call(recipes, "PrepareRecipe", [
      await struct(3002, { id: recipe }), await struct(3013, { id: "" })]);
    const [jobIdOut] = await call(auto, "StartSingleJob", [
      await struct(3015, { id: `node-meas-${k}` }), await struct(3004, { id: "node-part" }),
      await struct(3002, { id: "" }), await struct(3003, { id: "" }),
      { dataType: opcua.DataType.Variant, arrayType: opcua.VariantArrayType.Array, value: [] }]);
    const jobId = field(jobIdOut, "Id");
    const deadline = Date.now() + 120000;
    while (!events.some((e) => e.jobId === jobId)) {
      if (Date.now() > deadline) throw new Error(`no ResultReadyEvent for ${jobId}`);
      await new Promise((ok) => setTimeout(ok, 50));
    }
    const [, result] = await call(results, "GetResultById", [
      await struct(3021, { id: `r-${jobId}` }), { dataType: opcua.DataType.Int32, value: 0 }]);
    const pose = field(result, "ResultContent")[0].value;
    jobs.push({
      jobId, prepared: field(internal, "Id"),
      event: events.find((e) => e.jobId === jobId),
      result: { jobId: field(field(result, "JobId"), "Id"),
                resultState: field(result, "ResultState"),
                measId: field(field(result, "MeasId"), "Id"),
                position_mm: Array.from(field(pose, "position_mm")),
                rotvec_rad: Array.from(field(pose, "rotvec_rad")) } });
  }
  console.log(JSON.stringify({ facts: { checked, mismatches }, jobs }));
  await subscription.terminate();
  await session.close();
  await client.disconnect();
}

main().catch((err) => { console.error(String(err && err.stack || err)); process.exit(1); });
