// An OPC UA client independent of the server's stack (node-opcua): calls a job-starting
// method, reads JobId/JobState in the very next request, stops the job, waits for its end.
// Prints one JSON line: {"n": N, "consistent": K, "mismatches": [...], "events": E}.
// Usage: node node_opcua_jobs.js ENDPOINT USER PASSWORD N
const opcua = require("node-opcua");

async function main() {
  const [endpoint, user, password, nText] = process.argv.slice(2);
  const n = parseInt(nText, 10);
  const client = opcua.OPCUAClient.create({
    endpointMustExist: false,
    securityMode: opcua.MessageSecurityMode.None,
    securityPolicy: opcua.SecurityPolicy.None,
    connectionStrategy: { maxRetry: 2, initialDelay: 200 },
  });
  await client.connect(endpoint);
  const session = await client.createSession({
    type: opcua.UserTokenType.UserName, userName: user, password });
  const objects = await session.browse("ns=0;i=85");
  const cellRef = objects.references.find((r) => r.browseName.name === "Cell");
  const cellId = cellRef.nodeId;
  const children = await session.browse(cellId.toString());
  const ids = {};
  for (const r of children.references) ids[r.browseName.name] = r.nodeId;
  const read = async (...names) => {
    const dvs = await session.read(names.map((name) => ({
      nodeId: ids[name], attributeId: opcua.AttributeIds.Value })));
    return dvs.map((dv) => dv.value.value);
  };
  // JobEnded events from the Cell object
  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50, publishingEnabled: true,
    requestedMaxKeepAliveCount: 20, requestedLifetimeCount: 600 });
  const fields = ["EventType", "Message", "JobId", "JobState", "ErrorCode"];
  const item = await subscription.monitor(
    { nodeId: cellId, attributeId: opcua.AttributeIds.EventNotifier },
    { queueSize: 1000, filter: opcua.constructEventFilter(fields) },
    opcua.TimestampsToReturn.Both);
  const ended = new Map();
  item.on("changed", (values) => {
    const jobId = values[2].value;
    if (jobId) ended.set(jobId, { state: values[3].value, error: values[4].value });
  });
  let consistent = 0;
  const mismatches = [];
  const started = [];
  for (let i = 0; i < n; i++) {
    const res = await session.call({
      objectId: cellId, methodId: ids["Approach"],
      inputArguments: [{ dataType: opcua.DataType.Double, value: 40.0 },
                       { dataType: opcua.DataType.String, value: "" }] });
    const [code, message, jobId] = res.outputArguments.map((v) => v.value);
    if (code !== "ok") { mismatches.push({ i, code, message }); continue; }
    const [readId, readKind, readState] = await read("JobId", "JobKind", "JobState");
    if (readId === jobId && readKind === "approach" && readState === "running") consistent++;
    else mismatches.push({ i, jobId, readId, readKind, readState });
    started.push(jobId);
    await session.call({ objectId: cellId, methodId: ids["Stop"], inputArguments: [] });
    // wait for the end: state and result together
    const deadline = Date.now() + 30000;
    for (;;) {
      const [id2, state2, result2] = await read("JobId", "JobState", "JobResult");
      if (id2 === jobId && state2 !== "running") {
        const r = JSON.parse(result2);
        if (r.job_id !== jobId || r.state !== state2) {
          mismatches.push({ i, jobId, endState: state2, result: r });
        }
        break;
      }
      if (Date.now() > deadline) { mismatches.push({ i, jobId, timeout: true }); break; }
      await new Promise((ok) => setTimeout(ok, 10));
    }
  }
  const deadline = Date.now() + 5000;
  while (Date.now() < deadline && started.some((id) => !ended.has(id))) {
    await new Promise((ok) => setTimeout(ok, 50));
  }
  const events = started.filter((id) => ended.has(id)).length;
  const cancelled = started.filter((id) => (ended.get(id) || {}).state === "cancelled").length;
  console.log(JSON.stringify({ n, consistent, mismatches, events, cancelled }));
  await subscription.terminate();
  await session.close();
  await client.disconnect();
}

main().catch((err) => { console.error(String(err && err.stack || err)); process.exit(1); });
