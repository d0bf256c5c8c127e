// node-opcua's client as the independent OPC UA client of tests/e2e/test_opcua_node_client.py.
// Usage: node client.js '<json>' with {endpoint, security: "None" | "SignAndEncrypt", user, password,
// certificate, privateKey, applicationUri, pki, steps: [...]}; prints one JSON object: the result of
// each step, or {error} when the connection or the session failed.
"use strict";
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, UserTokenType,
  ClientSubscription, ClientMonitoredItem, TimestampsToReturn,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

function shown(dataValue) {
  return {
    value: dataValue.value && dataValue.value.value !== undefined ? dataValue.value.value : null,
    dataType: dataValue.value ? DataType[dataValue.value.dataType] : null,
    status: dataValue.statusCode.name,
    sourceTimestamp: dataValue.sourceTimestamp ? dataValue.sourceTimestamp.getTime() : null,
    serverTimestamp: dataValue.serverTimestamp ? dataValue.serverTimestamp.getTime() : null,
  };
}

async function step(session, s, namespace) {
  const id = (text) => `ns=${namespace};s=${text}`;
  switch (s.op) {
    case "browse": {
      const result = await session.browse(s.node === "Objects" ? "ns=0;i=85" : id(s.node));
      return result.references.map((r) => r.browseName.name);
    }
    case "read": {
      const values = await session.read(s.nodes.map((n) => ({ nodeId: id(n), attributeId: AttributeIds.Value })));
      return Object.fromEntries(s.nodes.map((n, i) => [n, shown(values[i])]));
    }
    case "access": {
      const values = await session.read(s.nodes.map((n) => ({ nodeId: id(n), attributeId: AttributeIds.AccessLevel })));
      return Object.fromEntries(s.nodes.map((n, i) => [n, values[i].value.value]));
    }
    case "write": {
      const status = await session.write({
        nodeId: id(s.node), attributeId: AttributeIds.Value,
        value: { value: { dataType: DataType[s.type], value: s.value } },
      });
      return status.name;
    }
    case "subscribe": {
      const subscription = ClientSubscription.create(session, {
        requestedPublishingInterval: s.publishing || 100, requestedLifetimeCount: 1000,
        requestedMaxKeepAliveCount: 10, maxNotificationsPerPublish: 0, publishingEnabled: true, priority: 1,
      });
      const changes = [];
      const item = ClientMonitoredItem.create(subscription, { nodeId: id(s.node), attributeId: AttributeIds.Value },
        { samplingInterval: s.sampling || 100, queueSize: 100, discardOldest: true }, TimestampsToReturn.Both);
      item.on("changed", (dv) => changes.push(shown(dv)));
      await sleep(s.seconds * 1000);
      await subscription.terminate();
      return changes;
    }
    case "sleep":
      await sleep(s.seconds * 1000);
      return null;
    default:
      throw new Error(`unknown step ${s.op}`);
  }
}

async function main() {
  const options = JSON.parse(process.argv[2]);
  const secure = options.security === "SignAndEncrypt";
  const client = OPCUAClient.create({
    applicationName: "slc-gateway e2e (node-opcua)",
    applicationUri: options.applicationUri,
    endpointMustExist: false,
    securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
    securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
    certificateFile: options.certificate,
    privateKeyFile: options.privateKey,
    clientCertificateManager: new OPCUACertificateManager({
      rootFolder: options.pki, automaticallyAcceptUnknownCertificate: true,
    }),
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    requestedSessionTimeout: 60000,
  });
  const out = { steps: [] };
  try {
    await client.connect(options.endpoint);
    const identity = options.user
      ? { type: UserTokenType.UserName, userName: options.user, password: options.password }
      : { type: UserTokenType.Anonymous };
    const session = await client.createSession(identity);
    const namespaces = (await session.readNamespaceArray());
    const namespace = namespaces.indexOf("urn:slc-gateway");
    for (const s of options.steps) {
      out.steps.push(await step(session, s, namespace));
    }
    await session.close();
  } catch (err) {
    out.error = String(err && err.message ? err.message : err);
  } finally {
    await client.disconnect();
  }
  process.stdout.write(JSON.stringify(out) + "\n");
}

main().catch((err) => { process.stdout.write(JSON.stringify({ error: String(err) }) + "\n"); process.exit(1); });
