#!/bin/sh
# SeaweedFS for the datagen cluster: one identity (S3_ACCESS_KEY / S3_SECRET_KEY from the
# environment; any other key is refused), data on /data, S3 on :8333, bucket $DATAGEN_BUCKET made
# once the gateway answers. `weed` runs as a child so that this shell can make the bucket; TERM and
# INT are passed on to it, and the container ends when it does.
set -eu
: "${S3_ACCESS_KEY:?S3_ACCESS_KEY is not set (.env)}"
: "${S3_SECRET_KEY:?S3_SECRET_KEY is not set (.env)}"
BUCKET=${DATAGEN_BUCKET:-datasets}
umask 077
mkdir -p /run/seaweedfs /data
cat >/run/seaweedfs/s3.json <<JSON
{"identities": [{"name": "datagen",
  "credentials": [{"accessKey": "${S3_ACCESS_KEY}", "secretKey": "${S3_SECRET_KEY}"}],
  "actions": ["Admin", "Read", "List", "Tagging", "Write"]}]}
JSON
rm -f /run/seaweedfs/ready
weed server -dir=/data -ip=127.0.0.1 -ip.bind=0.0.0.0 -master.telemetry=false \
    -master.volumeSizeLimitMB="${S3_VOLUME_SIZE_MB:-256}" -volume.max=0 -volume.preStopSeconds=0 \
    -filer -s3 -s3.port=8333 -s3.port.iceberg=0 -s3.port.lance=0 -s3.config=/run/seaweedfs/s3.json &
pid=$!
trap 'kill -TERM $pid 2>/dev/null' TERM INT
i=0
until echo "s3.bucket.list" | weed shell -master=127.0.0.1:9333 >/dev/null 2>&1; do
    i=$((i + 1)); [ $i -lt 120 ] || { echo "seaweedfs: not ready after 120 s" >&2; kill -TERM $pid; exit 1; }
    kill -0 $pid 2>/dev/null || { wait $pid; exit $?; }
    sleep 1
done
if ! echo "s3.bucket.list" | weed shell -master=127.0.0.1:9333 2>/dev/null | grep -q "^  $BUCKET\b"; then
    echo "s3.bucket.create -name $BUCKET" | weed shell -master=127.0.0.1:9333 >/dev/null
fi
echo "seaweedfs: S3 on :8333, bucket $BUCKET"
touch /run/seaweedfs/ready
status=0
wait $pid || status=$?
# a TERM interrupts the first wait: wait again for weed's own end
kill -0 $pid 2>/dev/null && { wait $pid || status=$?; }
exit $status
