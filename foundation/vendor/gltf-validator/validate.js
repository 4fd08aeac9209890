// Validate one .glb/.gltf file with the Khronos validator; print its JSON report on stdout.
const fs = require('fs');
const path = require('path');
const validator = require('./index.js');

const file = process.argv[2];
const bytes = new Uint8Array(fs.readFileSync(file));
validator.validateBytes(bytes, {
    uri: path.basename(file),
    maxIssues: 1000,
    externalResourceFunction: (uri) => new Promise((resolve, reject) => {
        fs.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)), (err, data) => {
            if (err) { reject(err.toString()); } else { resolve(new Uint8Array(data)); }
        });
    }),
}).then((report) => {
    process.stdout.write(JSON.stringify(report));
}).catch((err) => {
    process.stderr.write(String(err) + '\n');
    process.exit(1);
});
