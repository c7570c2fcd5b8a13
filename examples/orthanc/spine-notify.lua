-- Orthanc → landmarking: when a DX or CR series of a radiograph becomes stable (no new instance
-- for "StableAge" seconds), POST its study, series and instance UIDs as JSON to the URL in the
-- environment variable SPINE_NOTIFY_URL (the integrator's landmark tool, or a script that runs
-- `spine submit`). The service's own results (Manufacturer "spine-reconstruction", modalities SR
-- and OT) are not announced. Uses only Orthanc's built-in Lua (Debian's orthanc package):
-- OnStableSeries, RestApiGet, ParseJson, DumpJson, HttpPost.

local notify_url = os.getenv("SPINE_NOTIFY_URL")

function OnStableSeries(seriesId, tags, metadata)
   if notify_url == nil or notify_url == "" then
      return
   end
   local modality = tags["Modality"]
   if modality ~= "DX" and modality ~= "CR" then
      return
   end
   local series = ParseJson(RestApiGet("/series/" .. seriesId))
   local study = ParseJson(RestApiGet("/studies/" .. series["ParentStudy"]))
   local instances = ParseJson(RestApiGet("/series/" .. seriesId .. "/instances"))
   local uids = {}
   for i, instance in pairs(instances) do
      if instance["MainDicomTags"]["SOPInstanceUID"] ~= nil then
         table.insert(uids, instance["MainDicomTags"]["SOPInstanceUID"])
      end
   end
   local body = {
      study_instance_uid = study["MainDicomTags"]["StudyInstanceUID"],
      series_instance_uid = tags["SeriesInstanceUID"],
      sop_instance_uids = uids,
      modality = modality,
      accession_number = study["MainDicomTags"]["AccessionNumber"],
      patient_id = study["PatientMainDicomTags"]["PatientID"],
      orthanc_series_id = seriesId
   }
   HttpPost(notify_url, DumpJson(body, true), { ["Content-Type"] = "application/json" })
end
